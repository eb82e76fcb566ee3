"""The docs are a manual whose every result can be regenerated.

- every result file under docs/results/ is written by a Make target's command (its path, or a loop or
  variable that expands to it, is an output of some recipe line), and each JSON one records its
  provenance: the command, the commit and the date;
- no JSON file under docs/ lies outside docs/results/;
- every relative link and image in docs/**/*.md and README.md points to a file that exists, and every
  ``#anchor`` into a markdown file to one of its headings (GitHub's slugs);
- no heading repeats within a page;
- the generated sections of the benchmark pages are what the report code writes from the result files
  (the fine-tuning sections' headings and commands, the HitL sections whole).

Plain text parsing, no network, no Make run, nothing rerun.
"""

from __future__ import annotations

import itertools
import re
import shlex
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS = DOCS / "results"

# --- the Makefile's outputs -----------------------------------------------------------------------

ASSIGN = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*(?::=|\?=|\+=|=)\s*(.*)$")
RULE = re.compile(r"^([A-Za-z0-9_.%/-]+(?:\s+[A-Za-z0-9_.%/-]+)*)\s*:(?!=)")
MAKE_VAR = re.compile(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)|\$\{([A-Za-z_][A-Za-z0-9_]*)\}")
LOOP = re.compile(r"\bfor\s+([A-Za-z_][A-Za-z0-9_]*)\s+in\s+([^;]*?)\s*;\s*do\b")
SHELL_VAR = re.compile(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?")
# options whose value is a file the command writes
OUT_OPTIONS = ("--out", "--report")


def _logical_lines(text: str) -> list[str]:
    """The Makefile's lines with backslash continuations joined (a recipe's continuation lines keep
    their leading tab, as Make passes them to the shell)."""
    out, cur = [], ""
    for raw in text.splitlines():
        if raw.endswith("\\"):
            cur += raw[:-1] + " "
            continue
        out.append(cur + raw)
        cur = ""
    if cur:
        out.append(cur)
    return out


def parse_makefile(text: str) -> dict[str, list[str]]:
    """target -> its recipe lines, Make's variables expanded and ``$$`` turned into the shell's ``$``."""
    variables: dict[str, str] = {}
    recipes: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in _logical_lines(text):
        if line.startswith("\t"):
            if current is not None:
                current.append(line.strip())
            continue
        stripped = line.split("#", 1)[0].rstrip() if not line.lstrip().startswith("#") else ""
        if not stripped:
            continue
        if m := ASSIGN.match(stripped):
            variables[m.group(1)] = m.group(2).strip()
            continue
        if m := RULE.match(stripped):
            current = []
            for target in m.group(1).split():
                recipes[target] = current
            continue
        current = None

    def expand(s: str, depth: int = 0) -> str:
        if depth > 10:
            return s
        new = MAKE_VAR.sub(lambda m: variables.get(m.group(1) or m.group(2), ""), s.replace("$$", "\0"))
        new = new.replace("\0", "$$")
        return new if new == s else expand(new, depth + 1)

    return {t: [expand(line).replace("$$", "$") for line in lines] for t, lines in recipes.items()}


def _strip_quotes(token: str) -> str:
    return token.strip().strip("\"'").rstrip(";")


def outputs_of(line: str) -> set[str]:
    """The files one recipe line writes: the targets of ``>`` redirections and the values of ``--out``
    and ``--report`` (``hitl report sanity --out X.md`` writes ``X.json`` beside it too). A shell
    loop's variable is expanded over its words; an output still holding a ``$`` matches nothing."""
    found: set[str] = set()
    for m in re.finditer(r"(?<![0-9&])>(?!>)\s*([^\s;|&)]+)", line):
        found.add(_strip_quotes(m.group(1)))
    words = line.replace(";", " ; ").split()
    for i, word in enumerate(words[:-1]):
        if word in OUT_OPTIONS:
            found.add(_strip_quotes(words[i + 1]))
            if "report" in words[:i] and "sanity" in words[:i] and words[i + 1].endswith(".md"):
                found.add(_strip_quotes(words[i + 1])[: -len(".md")] + ".json")
        elif word.startswith(tuple(o + "=" for o in OUT_OPTIONS)):
            found.add(_strip_quotes(word.split("=", 1)[1]))
    loops = {var: shlex.split(values) for var, values in LOOP.findall(line)}
    expanded: set[str] = set()
    for path in found:
        names = [v for v in dict.fromkeys(SHELL_VAR.findall(path)) if v in loops]
        if not names:
            expanded.add(path)
            continue
        for combo in itertools.product(*(loops[v] for v in names)):
            p = path
            for var, value in zip(names, combo, strict=True):
                p = re.sub(r"\$\{?" + var + r"\}?(?![A-Za-z0-9_])", value, p)
            expanded.add(p)
    return {p for p in expanded if "$" not in p}


def make_outputs(text: str) -> dict[str, set[str]]:
    """target -> the repository-relative files its recipe writes."""
    return {t: set().union(*(outputs_of(line) for line in lines)) for t, lines in parse_makefile(text).items()}


def _git_files(*paths: str) -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z", *paths], cwd=ROOT, capture_output=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return []
    return [ROOT / p for p in out.stdout.decode().split("\0") if p and (ROOT / p).is_file()]


def result_files() -> list[Path]:
    """Every result file: those git tracks and those not added yet (a filesystem walk)."""
    walked = [p for p in RESULTS.rglob("*") if p.is_file()] if RESULTS.is_dir() else []
    return sorted(set(_git_files("docs/results")) | set(walked))


def test_every_result_file_is_written_by_a_make_target():
    produced = set().union(*make_outputs((ROOT / "Makefile").read_text()).values())
    files = result_files()
    assert files, "no result files under docs/results/"
    orphans = [str(p.relative_to(ROOT)) for p in files if str(p.relative_to(ROOT)) not in produced]
    assert not orphans, "result files no Make target writes (add the command that made them):\n" + "\n".join(orphans)


def test_every_result_file_names_its_command_commit_and_date():
    """Each JSON result records what made it (``bench.provenance``): a non-empty command, the 40-hex commit
    and an ISO 8601 date."""
    import datetime
    import json

    bad = []
    for path in (p for p in result_files() if p.suffix == ".json"):
        prov = json.loads(path.read_text()).get("provenance")
        prov = prov if isinstance(prov, dict) else {}
        problems = []
        if not str(prov.get("command") or "").strip():
            problems.append("no command")
        if not re.fullmatch(r"[0-9a-f]{40}", str(prov.get("commit") or "")):
            problems.append(f"commit {prov.get('commit')!r}")
        try:
            datetime.datetime.fromisoformat(str(prov.get("date")))
        except ValueError:
            problems.append(f"date {prov.get('date')!r}")
        if problems:
            bad.append(f"{path.relative_to(ROOT)}: {', '.join(problems)}")
    assert not bad, "result files without their provenance:\n" + "\n".join(bad)


def test_the_makefile_parser_finds_redirections_options_and_loops():
    text = (
        "X := a b\n"
        "BIN := .venv/bin\n"
        "t: install\n"
        "\t$(BIN)/hitl bench fleet --quiet > docs/results/serving/fleet.json\n"
        "\tfor t in $(X); do $(BIN)/hitl assist --task $$t \\\n"
        "\t\t--json > docs/results/signals/assist-$$t.json || exit 1; done\n"
        "\t$(BIN)/hitl bench console --out docs/results/console/wire.json --quiet || true\n"
        "\t$(BIN)/hitl report sanity --lift runs/l --out docs/results/policy/sanity.md\n"
        '\tft="$(BIN)/hitl bench finetune --json" && $$ft --x > docs/results/finetune/x.json && \\\n'
        "\t\tfor n in 20 50; do $$ft > docs/results/finetune/tail-$$n.json || exit 1; done\n"
        "u:\n"
        "\techo $$HOME > docs/results/$$UNKNOWN.json\n"
    )
    out = make_outputs(text)
    assert out["t"] == {
        "docs/results/serving/fleet.json",
        "docs/results/signals/assist-a.json",
        "docs/results/signals/assist-b.json",
        "docs/results/console/wire.json",
        "docs/results/policy/sanity.md",
        "docs/results/policy/sanity.json",
        "docs/results/finetune/x.json",
        "docs/results/finetune/tail-20.json",
        "docs/results/finetune/tail-50.json",
    }
    assert out["u"] == set()  # an unexpanded variable produces nothing


def test_no_json_under_docs_outside_docs_results():
    stray = sorted(
        str(p.relative_to(ROOT))
        for p in set(DOCS.rglob("*.json")) | set(_git_files("docs"))
        if p.suffix == ".json" and p.is_file() and RESULTS not in p.parents
    )
    assert not stray, "JSON files under docs/ outside docs/results/:\n" + "\n".join(stray)


# --- links and headings ---------------------------------------------------------------------------

FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
INLINE_CODE = re.compile(r"`[^`]*`")


def pages() -> list[Path]:
    return sorted([ROOT / "README.md", *DOCS.rglob("*.md")])


def _prose_lines(text: str) -> list[str]:
    """The page's lines outside fenced code blocks (fenced lines come back empty, keeping numbers)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else line)
    return out


def headings(text: str) -> list[str]:
    return [m.group(2) for line in _prose_lines(text) if (m := HEADING.match(line))]


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading: the text without markup, lower case, punctuation dropped (letters,
    digits, ``_``, ``-`` and spaces kept), spaces turned into hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links keep their text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "")
    text = text.lower()
    text = "".join(c for c in text if c.isalnum() or c in "_- ")
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for h in headings(text):
        slug = github_slug(h)
        n = seen.get(slug, 0)
        out.add(slug if n == 0 else f"{slug}-{n}")
        seen[slug] = n + 1
    return out


def links(text: str) -> list[tuple[int, str]]:
    out = []
    for number, line in enumerate(_prose_lines(text), 1):
        for m in LINK.finditer(INLINE_CODE.sub("", line)):
            out.append((number, m.group(1)))
    return out


def test_github_slugs():
    assert github_slug("The object frame (`hitl train --frame object`)") == "the-object-frame-hitl-train---frame-object"
    assert github_slug("Why our numbers differ from the paper's") == "why-our-numbers-differ-from-the-papers"
    assert github_slug("ratio-0.8: full-trajectory at K = 100; takeover share 0.8") == (
        "ratio-08-full-trajectory-at-k--100-takeover-share-08"
    )
    assert anchors("# a\n## a\n```\n# a\n```\n") == {"a", "a-1"}


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_links_and_images_point_to_existing_files_and_headings(page):
    broken = []
    for number, target in links(page.read_text()):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
            continue  # http(s), mailto: not checked here
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            broken.append(f"line {number}: {target} (no such file)")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
            broken.append(f"line {number}: {target} (no heading #{anchor} in {dest.relative_to(ROOT)})")
    assert not broken, f"{page.relative_to(ROOT)}:\n" + "\n".join(broken)


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_heading_repeats_within_a_page(page):
    found = headings(page.read_text())
    repeated = sorted({h for h in found if found.count(h) > 1})
    assert not repeated, f"{page.relative_to(ROOT)} repeats headings:\n" + "\n".join(repeated)


# --- generated sections ---------------------------------------------------------------------------


def _section(page: Path, name: str) -> str:
    m = re.search(
        rf"<!-- hitl-bench:{re.escape(name)}:begin -->\n(.*?)\n<!-- hitl-bench:{re.escape(name)}:end -->",
        page.read_text(),
        re.S,
    )
    assert m, f"{page.relative_to(ROOT)} has no generated section {name!r}"
    return m.group(1)


def _reports(command: str) -> tuple[str, str] | None:
    """(report, section) of a recorded ``hitl bench`` command that wrote a report section."""
    words = shlex.split(command)
    if "--report" not in words:
        return None
    section = words[words.index("--section") + 1] if "--section" in words else None
    return words[words.index("--report") + 1], section


def test_fine_tuning_sections_carry_the_heading_the_code_writes():
    import json

    from bench.finetune.report import heading

    checked = 0
    for path in sorted((RESULTS / "finetune").glob("*.json")):
        result = json.loads(path.read_text())
        where = _reports(result["command"])
        if where is None:
            continue
        report, section = where
        body = _section(ROOT / report, section or "finetune")
        assert body.split("\n", 1)[0] == heading(section or "finetune", result), path.name
        assert f"Generated by `{result['command']}`" in body, path.name
        checked += 1
    assert checked


def test_hitl_sections_are_what_the_code_writes():
    import json

    from bench.hitl.docs import markdown

    for name in ("main", "ablations", "vision"):
        summary = json.loads((RESULTS / "hitl" / f"{name}.json").read_text())
        report, section = _reports(summary["provenance"]["command"])
        page = ROOT / report
        body = _section(page, section or "main")
        figures = [page.parent / f for f in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", body)]
        assert body == markdown(summary, figures, page, paper=name == "main", section=name)


def test_the_hitl_headline_is_what_the_code_writes_from_the_main_run_and_the_floor():
    import json

    from bench.hitl.headline import markdown as headline

    summary = json.loads((RESULTS / "hitl" / "main.json").read_text())
    words = shlex.split(summary["provenance"]["command"])
    assert "--floor" in words and "--default-signal" in words, "the main run writes the headline"
    floor = json.loads((ROOT / words[words.index("--floor") + 1]).read_text())
    report = ROOT / words[words.index("--report") + 1]
    body = _section(report, "headline")
    assert body == headline(summary, floor, words[words.index("--default-signal") + 1])
