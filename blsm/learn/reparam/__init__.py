"""Reparameterising a body model to a new template topology, and evaluating it (thesis ch. 3)."""
