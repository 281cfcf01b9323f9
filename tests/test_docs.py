"""The documentation works: every fenced code block in README.md and docs/*.md runs, and every
relative link, image and ``#anchor`` resolves.

How each fenced block is checked (a block must be labelled ``python``, ``bash`` or ``text``):

- ``text`` blocks are not code (the layout tree, sample output) and are the only ones skipped.
- ``python`` blocks run for real, the blocks of one page in order in one namespace (like a
  notebook; a fresh namespace per page), all pages in one fresh subprocess that imports this
  checkout's code (``PYTHONPATH``), runs in a temporary directory on one CPU device and compiles
  with ``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` (the runs are tiny: compiling is their cost).
  Before they run, the strings of :data:`SUBSTITUTIONS` are replaced, to shrink run sizes
  (fewer seeds and steps; ``_small(config)``, defined in every page's namespace, gives a config
  300-step epochs, one evaluation episode and 1,000-row buffers). Nothing else is added: a name
  a snippet uses must be defined by the snippets of its page, as a reader copying them needs.
- ``bash`` blocks: comments are dropped, ``\\``-continued lines joined, each line split at
  ``&&`` and each command checked by a rule (a command with no rule fails the test):
  ``gara-jax SUBCOMMAND ...`` and ``python -m experiments.MODULE ...`` run in this process, so
  that they run this checkout's code whatever the installed console script points to (its
  target, ``gara_jax.cli:main``, is checked against pyproject.toml), with ``--dry-run``
  added, which checks every argument and prints the plan without training or writing;
  ``python benchmarks/NAME.py ...`` and ``python examples/NAME.py ...`` run the script's
  ``main`` with ``--dry-run`` likewise; leading ``NAME=value`` assignments are set in the environment meanwhile; each must
  exit with status 0 and leave its working directory (a temporary one) empty.
  ``pip install -e ".[EXTRA]"`` is not run: the extras it names must exist in pyproject.toml.
  A line that runs ``pytest`` must be, verbatim, a line of ``.ci/run`` (CI runs the README's
  test command as written). :data:`SUBSTITUTIONS` applies to bash blocks too (``{tmp}``: the
  temporary directory).

Every entry of :data:`SUBSTITUTIONS` must be used by some block, so the table cannot rot.
docs/tests.md says the same in a paragraph.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LANGUAGES = ("python", "bash", "text")

# Applied, in this order, to every python and bash block before it runs (sizes only).
SUBSTITUTIONS = {
    "gara_jax.GaraConfig()": "_small(gara_jax.GaraConfig())",
    "gara_jax.HandcraftedConfig()": "_small(gara_jax.HandcraftedConfig())",
    "seeds=20,": "seeds=2,",
    "seeds=512,": "seeds=2,",
    "total_steps=120_000": "total_steps=600",
    "jax.random.key(0), 20)": "jax.random.key(0), 2)",
    "devices=4": "devices=1",  # the test machine may have one device
    "/shared/results/u_maze": "{tmp}/shared/results/u_maze",  # a path that may not exist
}

# Defined in every page's namespace before its python blocks run.
SMALL = '''
def _small(config):
    """``config`` with 300-step epochs, one evaluation episode and 1,000-row buffers."""
    import dataclasses
    low = dataclasses.replace(config.low, buffer_size=1000, learning_starts=100)
    sizes = {"steps_per_epoch": 300, "eval_episodes": 1, "low": low}
    if hasattr(config, "memory_capacity"):
        sizes["memory_capacity"] = 1000
    return dataclasses.replace(config, **sizes)
'''


@dataclass(frozen=True)
class Block:
    page: Path
    line: int  # 1-based line of the first code line
    lang: str
    code: str

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


_FENCE = re.compile(r"^(\s*)(`{3,})(.*)$")


def fenced_blocks(page: Path) -> list[Block]:
    """Every fenced block of ``page`` (an unclosed fence is an error)."""
    out, lines, i = [], page.read_text().splitlines(), 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, info = m.groups()
        start, body = i + 1, []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i][len(indent):] if lines[i].startswith(indent) else lines[i])
            i += 1
        assert i < len(lines), f"{page.relative_to(ROOT)}:{start}: unclosed code fence"
        out.append(Block(page, start + 1, info.strip(), "\n".join(body) + "\n"))
        i += 1
    return out


BLOCKS = [b for page in PAGES for b in fenced_blocks(page)]


def substitute(code: str, used: dict | None = None, tmp: str = "") -> str:
    for old, new in SUBSTITUTIONS.items():
        if old in code:
            if used is not None:
                used[old] = used.get(old, 0) + code.count(old)
            code = code.replace(old, new.replace("{tmp}", tmp))
    return code


def test_every_block_is_labelled():
    bad = [f"{b.where}: ```{b.lang}" for b in BLOCKS if b.lang not in LANGUAGES]
    assert not bad, f"label every fenced block {LANGUAGES} (text: not code): {bad}"


def test_every_substitution_is_used():
    used: dict = {}
    for b in BLOCKS:
        if b.lang in ("python", "bash"):
            substitute(b.code, used)
    assert set(used) == set(SUBSTITUTIONS), (
        f"unused SUBSTITUTIONS entries: {sorted(set(SUBSTITUTIONS) - set(used))}")


# ----------------------------------------------------------------------------------------------
# python blocks
# ----------------------------------------------------------------------------------------------

_RUNNER = textwrap.dedent('''
    import json, sys, time, traceback
    pages = json.load(sys.stdin)
    results = {}
    for page, blocks in pages.items():
        start = time.perf_counter()
        namespace = {"__name__": "__main__"}
        exec(compile(SMALL, "<test_docs: _small>", "exec"), namespace)
        for line, code in blocks:
            try:
                exec(compile("\\n" * (line - 1) + code, page, "exec"), namespace)
            except BaseException:
                results[page] = f"block at line {line} failed:\\n" + traceback.format_exc()
                break
        else:
            results[page] = "ok"
        print(f"{page}: {results[page].splitlines()[0]} ({time.perf_counter() - start:.1f} s)",
              file=sys.stderr, flush=True)
    print("RESULTS " + json.dumps(results))
''').replace("SMALL", repr(SMALL))

PYTHON_PAGES = sorted({str(b.page.relative_to(ROOT)) for b in BLOCKS if b.lang == "python"})


@pytest.fixture(scope="module")
def python_results(tmp_path_factory):
    """Run every page's python blocks in one fresh subprocess; page -> "ok" or the traceback."""
    pages: dict = {}
    for b in BLOCKS:
        if b.lang == "python":
            pages.setdefault(str(b.page.relative_to(ROOT)), []).append(
                (b.line, substitute(b.code)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    env.pop("XLA_FLAGS", None)  # one CPU device, whatever other tests set
    env["JAX_PLATFORMS"] = "cpu"
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"  # tiny runs: compiling fast is what counts
    proc = subprocess.run([sys.executable, "-c", _RUNNER], input=json.dumps(pages), text=True,
                          capture_output=True, cwd=tmp_path_factory.mktemp("python_blocks"),
                          env=env, timeout=600)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULTS ")]
    assert proc.returncode == 0 and lines, (
        f"the runner failed (status {proc.returncode}):\n{proc.stdout[-3000:]}\n"
        f"{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULTS "):])


@pytest.mark.parametrize("page", PYTHON_PAGES)
def test_python_blocks_run(page, python_results):
    assert python_results[page] == "ok", f"{page}: {python_results[page]}"


# ----------------------------------------------------------------------------------------------
# bash blocks
# ----------------------------------------------------------------------------------------------


def bash_lines(block: Block) -> list[tuple[int, str]]:
    """``(line, command line)`` of a bash block: comments dropped, continuations joined."""
    out, pending, first = [], "", 0
    for n, raw in enumerate(block.code.splitlines(), start=block.line):
        if not pending and (not raw.strip() or raw.lstrip().startswith("#")):
            continue
        if not pending:
            first = n
        if raw.rstrip().endswith("\\"):
            pending += raw.rstrip()[:-1] + " "
            continue
        out.append((first, (pending + raw).strip()))
        pending = ""
    assert not pending, f"{block.where}: a continued line never ends"
    return out


BASH = [(b, n, line) for b in BLOCKS if b.lang == "bash" for n, line in bash_lines(b)]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _commands(line: str) -> list[list[str]]:
    """The ``&&``-separated commands of a line, as argument lists (comments dropped)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars="&|;<>")
    lexer.whitespace_split, lexer.commenters = True, "#"
    out, current = [], []
    for token in lexer:
        if token == "&&":
            out.append(current)
            current = []
        else:
            assert not set(token) <= set("&|;<>"), f"only && may join commands: {line!r}"
            current.append(token)
    return [*out, current]


def _check_pip(args: list[str], where: str) -> None:
    extras = PYPROJECT["project"]["optional-dependencies"]
    targets = [a for a in args if a.startswith(".")]
    assert targets and "-e" in args, f"{where}: expected pip install -e .[EXTRAS]: {args}"
    for target in targets:
        m = re.fullmatch(r"\.(?:\[([\w,\s-]+)\])?", target)
        assert m, f"{where}: cannot read the install target {target!r}"
        for extra in filter(None, (e.strip() for e in (m.group(1) or "").split(","))):
            assert extra in extras, f"{where}: extra {extra!r} is not in pyproject.toml"


def _call_main(main, argv: list[str]) -> int:
    try:
        result = main(argv)
    except SystemExit as err:
        return err.code if isinstance(err.code, int) else 1
    return result if isinstance(result, int) else 0


def _load_script(path: Path):
    spec = importlib.util.spec_from_file_location(f"_docs_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _dry(argv: list[str]) -> list[str]:
    return argv if "--dry-run" in argv else [*argv, "--dry-run"]


def run_command(tokens: list[str], where: str, line: str) -> int | None:
    """Check one command by its rule; returns its exit status (None: checked, not run)."""
    env = {}
    while tokens and re.fullmatch(r"[A-Za-z_]\w*=.*", tokens[0]):
        name, value = tokens.pop(0).split("=", 1)
        env[name] = value
    assert tokens, f"{where}: an empty command in {line!r}"
    head, args = tokens[0], tokens[1:]
    if head == "python" and args[:1] == ["-m"] and args[1:2] == ["pip"]:
        assert args[2:3] == ["install"], f"{where}: only pip install has a rule: {line!r}"
        _check_pip(args[3:], where)
        return None
    if "pytest" in tokens:
        ci = (ROOT / ".ci" / "run").read_text().splitlines()
        assert line in ci, f"{where}: a pytest line must be a line of .ci/run, verbatim: {line!r}"
        return None
    with _environment(env):
        if head == "gara-jax":
            script = PYPROJECT["project"]["scripts"]["gara-jax"]
            assert script == "gara_jax.cli:main", script
            from gara_jax import cli

            return _call_main(cli.main, _dry(args))
        if head == "python" and args[:1] == ["-m"] and args[1].startswith("experiments."):
            return _call_main(importlib.import_module(args[1]).main, _dry(args[2:]))
        if head == "python" and args and args[0].startswith(("benchmarks/", "examples/")):
            path = ROOT / args[0]
            assert path.is_file(), f"{where}: no such script {args[0]}"
            return _call_main(_load_script(path).main, _dry(args[1:]))
    raise AssertionError(f"{where}: no rule checks this command (see tests/test_docs.py): "
                         f"{line!r}")


@contextlib.contextmanager
def _environment(env: dict):
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.parametrize("block,n,line", BASH,
                         ids=[f"{b.page.relative_to(ROOT)}:{n}" for b, n, _ in BASH])
def test_bash_line(block, n, line, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = substitute(line, tmp=str(tmp_path))
    where = f"{block.page.relative_to(ROOT)}:{n}"
    statuses = [run_command(tokens, where, line) for tokens in _commands(line)]
    assert all(s in (None, 0) for s in statuses), f"{where}: exit statuses {statuses}: {line!r}"
    assert not any(tmp_path.iterdir()), f"{where}: a dry run wrote {list(tmp_path.iterdir())}"


def test_dry_run_rejects_an_unknown_method(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    from gara_jax import cli

    assert cli.main(["reproduce", "--dry-run", "--methods", "gara,no_such_method"]) == 2
    assert "no_such_method" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_dry_run_checks_a_resume_against_the_saved_run(tmp_path, capsys):
    from experiments import u_maze

    out = tmp_path / "run"
    argv = ["--quick", "--methods", "handcrafted", "--out", str(out), "--dry-run"]
    args = u_maze._apply_defaults(u_maze.parse_args(argv))
    saved = out / "checkpoints" / "run_config.json"
    saved.parent.mkdir(parents=True)
    saved.write_text(json.dumps(u_maze.run_config(args, ["handcrafted"])))
    assert u_maze.main([*argv, "--resume"]) == 0
    assert "the arguments match" in capsys.readouterr().out
    assert u_maze.main([*argv, "--resume", "--seeds", "3"]) == 2
    assert "--resume: the arguments differ" in capsys.readouterr().err
    assert sorted(p.name for p in out.rglob("*")) == ["checkpoints", "run_config.json"]


# ----------------------------------------------------------------------------------------------
# links and anchors
# ----------------------------------------------------------------------------------------------

_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _without_blocks(page: Path) -> str:
    """``page`` without the bodies of its fenced blocks."""
    text = page.read_text()
    for b in fenced_blocks(page):
        text = text.replace(b.code, "")
    return text


def _prose(page: Path) -> str:
    """``page`` without its fenced blocks and inline code (links there are not links)."""
    return re.sub(r"`[^`\n]*`", "", _without_blocks(page))


def github_anchor(heading: str) -> str:
    """GitHub's anchor for a heading: markup dropped, lowercase, punctuation removed except
    ``-`` and ``_``, spaces to ``-``."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links: their text
    text = re.sub(r"[`*]", "", text).strip().lower()
    text = "".join(c for c in text if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict = {}
    out = set()
    for line in _without_blocks(page).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = github_anchor(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def test_github_anchor_rule():
    assert github_anchor("Checkpoints (`gara_jax.checkpoint`)") == "checkpoints-gara_jaxcheckpoint"
    assert github_anchor("Published HIRO's time") == "published-hiros-time"
    assert github_anchor("Why the greedy policy failed, and what changed") == (
        "why-the-greedy-policy-failed-and-what-changed")


LINKS = [(page, target) for page in PAGES for target in _LINK.findall(_prose(page))
         if not re.match(r"[a-z]+:", target)]


def test_the_pages_have_links():
    assert len(LINKS) > 20 and any(t.endswith(".png") for _, t in LINKS)


@pytest.mark.parametrize("page,target", LINKS,
                         ids=[f"{p.relative_to(ROOT)}->{t}" for p, t in LINKS])
def test_link_resolves(page, target):
    path, _, anchor = target.partition("#")
    file = (page.parent / path).resolve() if path else page
    where = f"{page.relative_to(ROOT)}: ({target})"
    assert file.exists(), f"{where}: no such file {file}"
    assert ROOT in file.parents or file == ROOT, f"{where}: points outside the repository"
    if anchor:
        assert file.suffix == ".md", f"{where}: an anchor into a file that is not markdown"
        assert anchor in anchors(file), (
            f"{where}: no heading of {file.relative_to(ROOT)} has the anchor #{anchor} "
            f"(it has {sorted(anchors(file))})")


def test_every_docs_page_is_linked_from_the_readme():
    linked = {(ROOT / t.partition("#")[0]).resolve() for p, t in LINKS if p == PAGES[0]}
    missing = [p.name for p in PAGES[1:] if p.resolve() not in linked]
    assert not missing, f"README.md links to no docs page named {missing}"
