"""Write one benchmark's section of ``docs/benchmarks.md`` without touching the others.

A section lives between ``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``; a new one is
appended. The file is replaced atomically.
"""

from __future__ import annotations

from pathlib import Path

HEADER = [
    "# Benchmarks",
    "",
    "All numbers are ratios measured side by side in one run; absolute times depend on the machine.",
    "",
]


def write_section(path: Path, name: str, title: str, script: str, lines: list[str], command: str | None = None) -> None:
    """Replace (or append) section ``name``: a ``## title`` heading, the command that made it
    (``make bench`` running ``script``, or ``command`` for a run outside ``make bench``), then ``lines``."""
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    made = command or f"`make bench` (runs `python {script} --out {path}`)"
    head = [f"## {title}", "", f"Command: {made}.", ""]
    block = "\n".join([begin, *head, *lines, end])
    text = path.read_text() if path.exists() else "\n".join(HEADER) + "\n"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
