from __future__ import annotations

from pathlib import Path

import pytest
from tiny_run import TINY

from synth.generate import generate


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    """:data:`tiny_run.TINY` generated once for the session (tests copy it before changing it)."""
    out = tmp_path_factory.mktemp("tiny")
    generate(TINY, out, progress=False)
    return out
