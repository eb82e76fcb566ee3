"""The generated sections of a benchmark page: each ``hitl bench … --report PAGE --section NAME`` run
rewrites only the text between its section's markers, so the hand-written text around it and the other
runs' sections stay as they are."""

from __future__ import annotations

from pathlib import Path


def replace_section(report: Path, section: str, body: str) -> Path:
    """Puts ``body`` between the ``hitl-bench:<section>`` markers of ``report``, keeping the hand-written
    text around them; a report without them gets them appended."""
    begin, end = f"<!-- hitl-bench:{section}:begin -->", f"<!-- hitl-bench:{section}:end -->"
    report.parent.mkdir(parents=True, exist_ok=True)
    text = report.read_text() if report.is_file() else ""
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = f"{head}{begin}\n{body}\n{end}{tail}"
    else:
        text = f"{text}{begin}\n{body}\n{end}\n"
    report.write_text(text)
    return report
