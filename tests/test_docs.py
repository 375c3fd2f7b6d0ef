"""The documentation holds together: README.md is a front page, its links and the docs' links resolve, every
``monai-probreg`` option the docs name exists, and CI finds its test command where ``.ci/run`` looks for it."""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
LINKED_DOCS = [README, *DOCS, ROOT / "bundle" / "docs" / "README.md"]
OPTION_DOCS = [README, *DOCS]
SUBCOMMANDS = ("register-batch", "register", "demo")  # longest first: "register" is a prefix of "register-batch"
COMMANDS = (*SUBCOMMANDS, "apply")  # SUBCOMMANDS share the option table; apply has options of its own
MAX_README_LINES = 150  # a product page read in five minutes (issue #51); the rest lives in docs/
CI_MARKER = "<!-- ci:test-command -->"

FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")
MD_LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
IMG_SRC = re.compile(r"<img\b[^>]*\bsrc\s*=\s*[\"']([^\"']+)[\"']", re.IGNORECASE)
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9]*(?:-[a-z0-9]+)*(?![\w])")
COMMAND = re.compile(r"\bmonai-probreg\s+(" + "|".join(COMMANDS) + r")\b")


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def links(text: str) -> list[str]:
    """Link targets of markdown links and images and of <img src>, outside code (inline code kept as a placeholder,
    so a link whose text is code still counts)."""
    prose = INLINE_CODE.sub("code", FENCE.sub("", text))
    return MD_LINK.findall(prose) + IMG_SRC.findall(prose)


def is_external(target: str) -> bool:
    return bool(re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE))  # http:, https:, mailto:, ...


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.MULTILINE):
        slug = github_slug(heading)
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def relative_links(doc: Path):
    for target in links(doc.read_text(encoding="utf-8")):
        if is_external(target) or target.startswith("#"):
            continue
        yield target


@pytest.mark.parametrize("doc", LINKED_DOCS, ids=_rel)
def test_relative_links_resolve(doc):
    assert doc.exists(), f"{_rel(doc)} is missing"
    missing = []
    for target in relative_links(doc):
        path = target.split("#", 1)[0].split("?", 1)[0]
        if not (doc.parent / path).exists():
            missing.append(target)
    assert not missing, f"{_rel(doc)}: links that resolve to nothing: {missing}"


@pytest.mark.parametrize("doc", LINKED_DOCS, ids=_rel)
def test_anchors_into_markdown_pages_exist(doc):
    bad = []
    text = doc.read_text(encoding="utf-8")
    for target in links(text):
        if is_external(target) or "#" not in target:
            continue
        path, anchor = target.split("#", 1)
        page = doc if not path else (doc.parent / path)
        if page.suffix == ".md" and page.exists() and anchor not in anchors(page):
            bad.append(target)
    assert not bad, f"{_rel(doc)}: anchors with no heading: {bad}"


def test_docs_pages_exist_and_readme_links_each():
    names = {p.name for p in DOCS}
    expected = {"accuracy.md", "speed.md", "uncertainty.md", "cli.md", "bundle.md", "design.md", "changelog.md"}
    assert expected <= names, f"missing docs pages: {sorted(expected - names)}"
    readme_targets = {t.split("#", 1)[0] for t in relative_links(README)}
    assert {f"docs/{n}" for n in expected} <= readme_targets, "README links every docs page"


def test_readme_is_a_front_page():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"


# --- the command's options ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def help_options() -> dict[str, set[str]]:
    """Every option string of each subcommand, from the parser ``monai-probreg`` runs (what ``--help`` prints)."""
    from monai_probreg.cli.main import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {
        name: {s for a in sub.choices[name]._actions for s in a.option_strings if s.startswith("--")}
        for name in COMMANDS
    }


def command_lines(text: str) -> list[tuple[str, str]]:
    """(subcommand, rest of the line) for every ``monai-probreg <sub> ...`` line, continuation lines joined and
    shell comments dropped."""
    joined = re.sub(r"\\\n", " ", text)
    found = []
    for line in joined.splitlines():
        for match in COMMAND.finditer(line):
            rest = line[match.end() :]
            rest = re.split(r"(?:^|\s)#\s", rest, maxsplit=1)[0]  # a shell comment
            rest = re.split(r"`|&&|;|\|", rest, maxsplit=1)[0]  # the end of an inline span or of the command
            found.append((match.group(1), rest))
    return found


def option_table_rows(text: str) -> list[tuple[dict[str, str], str]]:
    """Rows of a markdown table whose header is ``| option | register | register-batch | demo | ...``: the cell
    per subcommand and the option."""
    rows = []
    lines = text.splitlines()
    for i, line in enumerate(lines):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[:1] != ["option"] or not set(SUBCOMMANDS) <= set(cells):
            continue
        columns = {name: cells.index(name) for name in SUBCOMMANDS}
        for row in lines[i + 2 :]:
            if not row.strip().startswith("|"):
                break
            rcells = [c.strip() for c in row.strip().strip("|").split("|")]
            option = OPTION.search(rcells[0])
            assert option, f"an option table row without an option: {row}"
            rows.append(({name: rcells[col] for name, col in columns.items()}, option.group(0)))
    return rows


@pytest.mark.parametrize("doc", OPTION_DOCS, ids=_rel)
def test_options_on_command_lines_exist(doc, help_options):
    text = doc.read_text(encoding="utf-8")
    unknown = []
    for sub, rest in command_lines(text):
        for option in OPTION.findall(rest):
            if option not in help_options[sub]:
                unknown.append(f"monai-probreg {sub} {option}")
    assert not unknown, f"{_rel(doc)} names options that --help does not list: {sorted(set(unknown))}"


@pytest.mark.parametrize("doc", OPTION_DOCS, ids=_rel)
def test_option_tables_match_the_parser(doc, help_options):
    """An option table lists each subcommand's options, no more and no fewer."""
    rows = option_table_rows(doc.read_text(encoding="utf-8"))
    if not rows:
        pytest.skip(f"{_rel(doc)} has no option table")
    for sub in SUBCOMMANDS:
        listed = {option for cells, option in rows if cells[sub] not in ("", "–", "-")}
        assert listed == help_options[sub] - {"--help"}, (
            f"{_rel(doc)}, {sub}: in the table, not in --help: {sorted(listed - help_options[sub])}; "
            f"in --help, not in the table: {sorted(help_options[sub] - {'--help'} - listed)}"
        )


def test_the_cli_reference_has_the_option_table():
    assert option_table_rows((ROOT / "docs" / "cli.md").read_text(encoding="utf-8"))


@pytest.mark.parametrize("doc", [README, ROOT / "docs" / "cli.md"], ids=_rel)
def test_options_named_in_prose_exist(doc, help_options):
    """In the README and the command-line reference, every ``--option`` in inline code is the command's (bundle and
    benchmark options elsewhere use other pages; bundle overrides have underscores and are not matched)."""
    every = set().union(*help_options.values())
    prose = FENCE.sub("", doc.read_text(encoding="utf-8"))
    unknown = {
        o
        for span in INLINE_CODE.findall(prose)
        if "monai.bundle" not in span and "python " not in span
        for o in OPTION.findall(span)
        if o not in every
    }
    assert not unknown, f"{_rel(doc)} names options that no subcommand has: {sorted(unknown)}"


# --- CI ------------------------------------------------------------------------------------------------------------


def ci_command_as_ci_run_reads_it(text: str) -> str | None:
    """The awk rule of .ci/run in Python: after the marker line, the first line that starts with a lowercase letter."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if CI_MARKER in line:
            return next((text for text in lines[i + 1 :] if re.match(r"[a-z]", text)), None)
    return None


def test_ci_finds_the_test_command():
    text = README.read_text(encoding="utf-8")
    assert text.count(CI_MARKER) == 1
    command = ci_command_as_ci_run_reads_it(text)
    assert command is not None, "no command after the CI marker"
    assert "pip install" in command and "pytest" in command and '".[test]"' in command, command
    fences = [m.group(0) for m in FENCE.finditer(text)]
    assert any(command in fence for fence in fences), "the CI command is shown in a code block"


def test_ci_run_reads_the_same_command():
    """Run the awk program of .ci/run itself on the README, when awk is here."""
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    program = re.search(r"awk '([^']*)' README\.md", ci)
    assert program, ".ci/run no longer reads its command from README.md with awk: update this test"
    awk = shutil.which("awk")
    if awk is None:
        pytest.skip("no awk")
    out = subprocess.run([awk, program.group(1), str(README)], capture_output=True, text=True, timeout=30, check=True)
    assert out.stdout.strip() == ci_command_as_ci_run_reads_it(README.read_text(encoding="utf-8"))


# --- bundle command lines ------------------------------------------------------------------------------------------
CONFIG_FILE_ARG = re.compile(r"--config_file\s+(\"\[[^\]\n]*\]\"|'\[[^\]\n]*\]'|\S+)")
COMMAND_SOURCES = [
    *LINKED_DOCS,
    *sorted((ROOT / "bundle" / "configs").glob("*.yaml")),
    *sorted((ROOT / "monai_probreg").rglob("*.py")),
    *sorted((ROOT / "benchmarks").glob("*.py")),
    *sorted((ROOT / "experiments").glob("*.py")),
]


def test_documented_bundle_commands_read_each_overlay_after_its_base():
    """evaluate.yaml holds only what differs from inference.yaml: every documented ``--config_file`` naming it
    passes inference.yaml before it (monai_probreg.fitting.stages.OVERLAY_BASES)."""
    from monai_probreg.fitting.stages import OVERLAY_BASES

    checked, wrong = 0, []
    for path in COMMAND_SOURCES:
        for match in CONFIG_FILE_ARG.finditer(path.read_text(encoding="utf-8")):
            names = re.findall(r"([\w-]+\.yaml)\b", match.group(1))
            for overlay, base in OVERLAY_BASES.items():
                if overlay in names:
                    checked += 1
                    if base not in names or names.index(base) > names.index(overlay):
                        wrong.append(f"{_rel(path)}: --config_file {match.group(1)}")
    assert checked, "no documented command line runs an overlay: update this test"
    assert not wrong, wrong
