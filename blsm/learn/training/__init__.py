"""Learning the BLSM parameters from registrations (thesis Sec. 5.4.2-5.4.4, Eqs. 5.26-5.31)."""
