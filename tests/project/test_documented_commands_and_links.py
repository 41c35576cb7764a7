"""The documentation's commands and links are real.

Every line of every ```bash block in README.md, CONTRIBUTING.md, docs/*.md (guides) and docs/results/*.md
(measured figures) is checked:

* ``make T`` — ``T`` is a target of the Makefile;
* ``pip install -e '.[x]'`` / ``pip install 'histojax[x]'`` — the extras exist in pyproject.toml;
* ``python -m MOD ARGS`` / ``python path/script.py ARGS`` / ``histojax SUB ARGS`` — the module or script
  exists and its argparse parser accepts ARGS: the command runs in this process until its first
  ``ArgumentParser.parse_args``, which parses and then stops it (a dry parse: nothing is computed);
* anything else fails, so the docs show only commands that are checked.

Bash blocks preceded by ``<!-- docs-check: run -->`` are also run for real (in a scratch folder that sees
the repository's files). **Every** ```python block runs, each in a fresh interpreter, unless the line
before it is ``<!-- docs-check: skip (reason) -->`` — the reason, shown on the page, is required (a
skip mark without one fails); ``<!-- docs-check: run-slow -->`` blocks run only under ``make test-all``.
Relative links between pages must resolve, anchors included.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import runpy
import shlex
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GUIDES = sorted((ROOT / "docs").glob("*.md"))  # guides: short and current (no dated run records)
RESULTS = sorted((ROOT / "docs" / "results").glob("*.md"))  # dated measured figures, one page per topic
PAGES = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *GUIDES, *RESULTS]
GUIDE_MAX_LINES = 300

# Pages written in parallel on other branches, linked before they are merged. Links to these may
# dangle ONLY until they land: remove each name from this list when its page exists.
PENDING_PAGES: set[str] = set()

_MARK = re.compile(r"<!--\s*docs-check:\s*(run|run-slow)\s*-->")
_SKIP = re.compile(r"<!--\s*docs-check:\s*skip\s*\((?P<reason>[^)]*\S[^)]*)\)\s*-->")
_ANY_SKIP = re.compile(r"docs-check:\s*skip")


def _bash_blocks(page: Path) -> list[tuple[int, str | None, list[tuple[int, str]]]]:
    """``(first line number, mark or None, [(line number, command)])`` per ```bash block of ``page``;
    ``\\``-continued lines are joined, comments and blank lines dropped."""
    lines = page.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "```bash":
            before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            mark = _MARK.search(before)
            start, commands, pending, pending_line = i + 1, [], "", 0
            i += 1
            while i < len(lines) and lines[i].strip() != "```":
                text = lines[i]
                if not pending:
                    pending_line = i + 1
                if text.rstrip().endswith("\\"):
                    pending += text.rstrip()[:-1] + " "
                else:
                    command = (pending + text).strip()
                    pending = ""
                    if command and shlex.split(command, comments=True):
                        commands.append((pending_line, command))
                i += 1
            blocks.append((start, mark.group(1) if mark else None, commands))
        i += 1
    return blocks


def _all_commands():
    for page in PAGES:
        for _, _, commands in _bash_blocks(page):
            for line, command in commands:
                yield pytest.param(page, command, id=f"{page.relative_to(ROOT)}:{line}")


def _run_blocks():
    for page in PAGES:
        for start, mark, commands in _bash_blocks(page):
            if mark:
                marks = [pytest.mark.slow] if mark == "run-slow" else []
                yield pytest.param(page, commands, id=f"{page.relative_to(ROOT)}:{start}", marks=marks)


def _python_blocks():
    """Every ```python block of every page: run, run-slow (marked slow) or skipped with its page's reason."""
    for page in PAGES:
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.strip() != "```python":
                continue
            before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            end = lines.index("```", i + 1)
            marks = []
            if (mark := _MARK.search(before)) and mark.group(1) == "run-slow":
                marks = [pytest.mark.slow]
            elif skip := _SKIP.search(before):
                marks = [pytest.mark.skip(reason=f"the page says: {skip.group('reason').strip()}")]
            yield pytest.param("\n".join(lines[i + 1 : end]), id=f"{page.relative_to(ROOT)}:{i + 1}", marks=marks)


def _words(command: str) -> list[str]:
    """The command's words, without comments and leading ``VAR=value`` assignments."""
    words = shlex.split(command, comments=True)
    while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
        words.pop(0)
    return words


class _Parsed(BaseException):
    """Raised by the patched parse_args once the arguments parsed (not an Exception: CLIs catch those)."""


def _dry_parse(kind: str, target: str, args: list[str]) -> None:
    """Run a CLI in this process until it has parsed ``args``; fail if argparse refuses them."""
    original = argparse.ArgumentParser.parse_args

    def parse_and_stop(self, args=None, namespace=None):
        original(self, args, namespace)
        raise _Parsed

    err = io.StringIO()
    argv = sys.argv
    try:
        argparse.ArgumentParser.parse_args = parse_and_stop
        sys.argv = [target, *args]
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # runpy: "found in sys.modules" (already imported)
            if kind == "module":
                runpy.run_module(target, run_name="__main__", alter_sys=False)
            elif kind == "script":
                runpy.run_path(str(ROOT / target), run_name="__main__")
            else:  # the histojax entry point
                from histojax.cli import main

                status = main(args)
                assert status == 0, f"histojax {' '.join(args)} exited {status}: {err.getvalue()}"
                if {"-h", "--help"} & set(args):
                    return  # `histojax --help` prints its overview without argparse
    except _Parsed:
        return
    except SystemExit as e:
        assert e.code in (0, None), f"argparse refused {args}: {err.getvalue().strip()}"
        return
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] not in ("histojax", "data_tools", "baselines", "benchmarks", "experiments"):
            pytest.skip(f"needs the optional dependency {e.name}")
        raise
    finally:
        argparse.ArgumentParser.parse_args = original
        sys.argv = argv
    pytest.fail(f"{target} {' '.join(args)} finished without parsing its arguments with argparse")


def _makefile_targets() -> set[str]:
    return set(re.findall(r"^([A-Za-z0-9_.-]+):", (ROOT / "Makefile").read_text(), flags=re.M))


def _extras() -> set[str]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])


@pytest.mark.parametrize("page, command", list(_all_commands()))
def test_command_is_real(page, command):
    words = _words(command)
    assert words, command
    head, args = words[0], words[1:]
    if head == "make":
        targets = [a for a in args if "=" not in a and not a.startswith("-")]
        assert targets and set(targets) <= _makefile_targets(), f"unknown make target in {command!r}"
    elif head == "pip":
        assert args[:1] == ["install"], command
        extras = [e for a in args for m in re.finditer(r"\[([^\]]+)\]", a) for e in m.group(1).split(",")]
        assert extras, f"pip commands in the docs install the project's extras: {command!r}"
        assert set(extras) <= _extras(), f"unknown extra in {command!r}"
    elif head in ("python", "python3"):
        if args[:1] == ["-m"]:
            _dry_parse("module", args[1], args[2:])
        else:
            assert args and (ROOT / args[0]).is_file(), f"no script {args[:1]} for {command!r}"
            _dry_parse("script", args[0], args[1:])
    elif head == "histojax":
        _dry_parse("histojax", "histojax", args)
    else:
        pytest.fail(
            f"{command!r}: not a command tests/project/test_documented_commands_and_links.py can check (make, pip, python, histojax)"
        )


@pytest.mark.parametrize("page, commands", list(_run_blocks()))
def test_marked_blocks_run(page, commands, tmp_path):
    """Run the block's commands one after another in a scratch folder holding links to the repository's
    files, so relative paths work and outputs land in the scratch folder."""
    for entry in ROOT.iterdir():
        if entry.name not in (".git", ".venv", "runs", "out") and not entry.name.startswith("."):
            (tmp_path / entry.name).symlink_to(entry)
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for _, command in commands:
        all_words, words = shlex.split(command, comments=True), _words(command)
        assigned = dict(w.split("=", 1) for w in all_words[: len(all_words) - len(words)])  # VAR=value prefixes
        if words[0] in ("python", "python3"):
            argv = [sys.executable, *words[1:]]
        elif words[0] == "histojax":
            argv = [sys.executable, "-m", "histojax.cli", *words[1:]]
        else:
            pytest.fail(f"run blocks hold python / histojax commands only: {command!r}")
        done = subprocess.run(argv, cwd=tmp_path, env={**env, **assigned}, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, (
            f"{command!r} exited {done.returncode}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
        )


@pytest.mark.parametrize("code", list(_python_blocks()))
def test_python_blocks_run(code, tmp_path):
    """Every ```python block runs as it is, in a fresh interpreter (unless its page says why not)."""
    script = tmp_path / "snippet.py"
    script.write_text(code + "\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]


def test_skip_marks_give_a_reason():
    """A ``docs-check: skip`` mark must say why, and must sit right before a ```python block."""
    bad = []
    for page in PAGES:
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if _ANY_SKIP.search(line):
                after = next((lines[j] for j in range(i + 1, len(lines)) if lines[j].strip()), "")
                if not _SKIP.search(line) or after.strip() != "```python":
                    bad.append(f"{page.relative_to(ROOT)}:{i + 1}: {line.strip()}")
    assert not bad, "skip marks need a reason in parentheses and a ```python block after them: " + "; ".join(bad)


def test_skip_mark_syntax():
    assert _SKIP.search("<!-- docs-check: skip (needs rejax) -->").group("reason") == "needs rejax"
    assert not _SKIP.search("<!-- docs-check: skip -->") and not _SKIP.search("<!-- docs-check: skip ( ) -->")
    assert _ANY_SKIP.search("<!-- docs-check: skip -->")


def _anchor(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    anchors, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"#{1,6}\s+(.*)", line)):
            anchors.add(_anchor(m.group(1)))
    return anchors


def _links(page: Path):
    text, fenced_free = page.read_text(), []
    fenced = False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced:
            fenced_free.append(line)
    for m in re.finditer(r"\[[^\]]*\]\(([^)\s]+)\)", "\n".join(fenced_free)):
        target = m.group(1)
        if not re.match(r"[a-z]+:", target):
            yield target


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve(page):
    for target in _links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        rel = os.path.relpath(dest, ROOT)
        if not dest.exists():
            assert rel in PENDING_PAGES, f"{page.name}: link to missing {target!r}"
            continue
        if anchor:
            assert anchor in _anchors(dest), f"{page.name}: no heading #{anchor} in {rel}"


def test_checker_refuses_what_is_wrong(tmp_path):
    """The checks can fail: unknown options, subcommands and scripts, and dangling anchors are caught."""
    for kind, target, args in [
        ("module", "data_tools", ["build", "x.svs", "--no-such-option"]),
        ("histojax", "histojax", ["train", "--algo", "ppo", "--bogus", "1"]),
        ("script", "benchmarks/throughput.py", ["--batchez", "1"]),
    ]:
        with pytest.raises(AssertionError, match="refused|exited"):
            _dry_parse(kind, target, args)
    page = tmp_path / "page.md"
    page.write_text("# A heading: with `code`, punctuation\n\n[x](#a-heading-with-code-punctuation) [y](#nope)\n")
    assert _anchors(page) == {"a-heading-with-code-punctuation"}
    assert list(_links(page)) == ["#a-heading-with-code-punctuation", "#nope"]
    assert _words("XLA_FLAGS=--x=4 python -m m --a 1  # note") == ["python", "-m", "m", "--a", "1"]


def test_pending_pages_list_is_current():
    """A pending page that has landed must leave PENDING_PAGES (so its links are checked)."""
    assert not [p for p in PENDING_PAGES if (ROOT / p).exists()], "remove landed pages from PENDING_PAGES"


@pytest.mark.parametrize("page", GUIDES, ids=lambda p: str(p.relative_to(ROOT)))
def test_guides_are_short(page):
    """A guide page stays readable: at most GUIDE_MAX_LINES lines (dated run records go to docs/results/)."""
    n = len(page.read_text().splitlines())
    assert n <= GUIDE_MAX_LINES, (
        f"{page.relative_to(ROOT)}: {n} lines, more than {GUIDE_MAX_LINES}; move run records to docs/results/"
    )


def test_results_pages_say_where_they_were_measured():
    """Each results page opens with one "Measured on" header: machine, JAX, histojax, date."""
    assert RESULTS, "no docs/results/ pages"
    for page in RESULTS:
        head = "\n".join(page.read_text().splitlines()[:8])
        assert head.count("**Measured on**") == 1, f"{page.relative_to(ROOT)}: no single **Measured on** header"
        for word in ("JAX", "histojax"):
            assert word in head, f"{page.relative_to(ROOT)}: its Measured-on header does not name {word}"
        assert re.search(r"\bCPU\b|\bGPU\b|NVIDIA|\bTPU\b", head), (
            f"{page.relative_to(ROOT)}: its Measured-on header does not name the machine (CPU or GPU model)"
        )
        assert re.search(r"20\d\d-\d\d-\d\d", head), f"{page.relative_to(ROOT)}: its header gives no date"


def test_readme_is_the_front_door():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    first = _bash_blocks(ROOT / "README.md")[0][2]
    assert [c.split("#")[0].strip() for _, c in first] == ["make demo", "make test"]
    linked = {os.path.relpath((ROOT / t.partition("#")[0]).resolve(), ROOT) for t in _links(ROOT / "README.md")}
    pages = {str(p.relative_to(ROOT)) for p in PAGES[1:]} | PENDING_PAGES
    assert pages <= linked, f"docs pages not linked from the README: {sorted(pages - linked)}"


# Words about how the work was done rather than about the product: which session or round of work a figure
# came from, how much time was left, which hardware was (not) lent. Results say their date, version, command,
# machine ("shared 2-core x86_64 CPU") and wall time instead.
_PROCESS_WORDS = re.compile(
    r"\bsessions?\b|\brounds? of work\b|\brounds? \d|\b(this|that|first|second|third|fourth|fifth|sixth|seventh|"
    r"eighth|ninth|tenth|previous|last|next) round\b|\b(was|were|is|are|not) (been )?lent\b|\blent (a |an )?"
    r"(gpu|tpu|device|machine|accelerator)|\ba lent (gpu|tpu|device|machine)|\btime (was )?left\b|\btime (this|the|"
    r"that) \w+ had\b|\bhad no (gpu|tpu|accelerator)\b|\bno (gpu|tpu|accelerator) (was|has been|is) "
    r"(lent|available|given)|\bdevice tool\b|\bengineers?\b|\bdid not fit (this|the) \w+\b",
    flags=re.IGNORECASE,
)


def _process_words(text: str) -> list[str]:
    return [
        f"{n}: {m.group(0)!r}" for n, line in enumerate(text.splitlines(), 1) for m in _PROCESS_WORDS.finditer(line)
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_speak_of_the_product_not_the_work(page):
    """No page says how the work was done (sessions, rounds of work, time left, hardware not lent)."""
    hits = _process_words(page.read_text())
    assert not hits, f"{page.relative_to(ROOT)} speaks of the work, not the product (line: words): {hits}"


def test_process_words_are_caught():
    """The scan finds the phrases it is for, and leaves product words alone."""
    for bad in [
        "the sixth session's agents",
        "Measured in this session",
        "the fifth round added",
        "rounds 3–4",
        "No GPU was lent.",
        "on a lent GPU",
        "the time this session had left",
        "the time left",
        "the sessions that wrote this page had no GPU",
        "six engineers shared the cores",
        "the device tool reported none",
        "which did not fit this session",
    ]:
        assert _process_words(bad), bad
    for fine in [
        "the normal slide that lent it its tissue",
        "round(x / stride)",
        "dealt round-robin",
        "a shared 2-core x86_64 CPU",
        "the one cache helper",
        "4 processes × 6 rounds in the slow run",
        "Measured 2026-11-24, histojax 0.1.0, JAX 0.10.2",
    ]:
        assert not _process_words(fine), fine
