"""Every command line the documentation gives for one of the repository's scripts is accepted by
that script's own argument parser: each flag exists, each value has the type and choices the
parser takes. Nothing trains or runs: only the parser is called.

Which lines: README.md, docs/*.md and examples/**/README*.md; a line (fenced or indented code,
or an inline `code` span, which may wrap across lines of a paragraph) that runs
examples/**.py or benchmarks/*.py, as `python SCRIPT ...`, after environment assignments
(`PYTHONPATH=. python ...`), under `torchrun [its options] SCRIPT ...`, or as a bare
`SCRIPT --flag ...` span, with trailing-backslash continuations joined; several commands on one
line are split at `&&`, `;`, `||` and a pipe.

How each script's parser is reached (SCRIPTS below, by name; a documented script not listed
there fails the test, so a new script has to be placed):
- "parse_args": the module (loaded with importlib, as tests/test_example_resume.py does) has
  parse_args(argv); it is called, so its post-parse checks (ap.error) run too.
- "main": the parser is built inside main() or under `if __name__ == "__main__"` with no separate
  function; the file is run as __main__ (runpy) with sys.argv set, and
  argparse.ArgumentParser.parse_args is wrapped so that the N-th successful parse (N = 1, or 2 for
  bench_view_cost.py and probe_view_cells.py, whose second parse is the example's parser on the flags after `--`)
  stops the script with the namespace before any work. Checks a main() makes after its parse
  are not reached. Every script a doc runs has a parser reached this way: NOT_PARSED (scripts
  skipped by name, with the reason) is empty.
Paths that only exist on the author's machine: the argparse type functions that check existence,
mvgs_plugin.cli.scene_folder (--data) and mvgs_plugin.cli.checkpoint_file (--resume), are
monkeypatched to return Path(text) for any string before a script is loaded (the scripts import
them by name, common_args looks them up in cli at call time); no other type or choice is touched.

Shell notation: `$VAR`/`${VAR}` take the file's last assignment before the line (`VAR=...`,
`for VAR in first ...`); `{a,b}` is brace-expanded and `*` globbed in the repository (kept as
written when nothing matches, as bash does); an optional `[...]` group is included, its ` | `
alternatives one per variant, as are `a|b|c` choice words (every variant is parsed); a standalone
`...` as the first argument stands for the previous command of the same script in the same file.
A trailing `...` (the rest elided) is dropped and the flags given are checked; such a line and a
bare `SCRIPT --flags` span are fragments, for which argparse's "the following arguments are
required" alone is not a failure (the required flag is named elsewhere in the text).
A documented placeholder after a flag (`--seed S`, `--budget B`, ...) is replaced by a value of
the kind the docs say it stands for (PLACEHOLDERS); a placeholder after a path flag is kept as a
path string. A line with any other placeholder is skipped with its reason, and the test asserts
that at least 80 % of the lines found were checked. One assertion at the end lists every failing
doc line (file:line, the command as parsed, argparse's message); a documented script that does
not exist, or that SCRIPTS does not place, is a failure too. tools/*.py (make_scene.py) are not covered.
Run this file as a script to print every command found and the argument lists parsed.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import importlib.util
import io
import itertools
import re
import runpy
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

import mvgs_plugin.cli as cli

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "examples").glob("**/README*.md"))]

# How each script's parser is reached (module docstring); 2 = bench_view_cost.py's second parse
SCRIPTS = {
    "examples/train_3dgs.py": "parse_args",
    "examples/train_scaffold.py": "parse_args",
    "examples/train_4dgs.py": "parse_args",
    "examples/ablation.py": "main",
    "examples/graphdeco_loop/train_mvgs.py": "main",
    "examples/gsplat_loop/simple_trainer.py": "main",
    "examples/gsplat_loop/simple_trainer_mvgs.py": "main",
    "examples/gsplat_loop/simple_trainer_chunked.py": "main",
    "examples/three_line_wrap/single_view.py": "main",
    "examples/three_line_wrap/mvgs.py": "main",
    **{f"benchmarks/{p.name}": "main" for p in sorted((ROOT / "benchmarks").glob("*.py"))},
}
PARSES_BEFORE_STOP = {"benchmarks/bench_view_cost.py": 2, "benchmarks/probe_view_cells.py": 2}
# Scripts whose parser cannot be called without running them: none at present (name -> reason)
NOT_PARSED: dict = {}
# Scripts that import an optional package: their lines are skipped, said so, when it is missing
NEEDS = {"examples/gsplat_loop/": "gsplat"}

# Flags whose value is a path: any string is a valid value here (the path is the author's)
PATH_FLAGS = {"--data", "--out", "--resume", "--init-cache", "--scenes", "--cost-scene", "--summary", "--json",
              "--before", "--table"}
# (flag, placeholder) -> the value it stands for in the docs (a valid value of that kind)
PLACEHOLDERS = {
    ("--seed", "S"): ["0"],              # "seeds 0 to 4"
    ("--budget", "B"): ["1000"],         # the budgets 1000 ... 10000
    ("--steps", "S"): ["1000"],          # the step counts of a sweep
    ("--steps", "N"): ["1000"],
    ("--max-gaussians", "N"): ["5000"],  # "N = a quarter of the disparity run's count"
    ("--background-points", "N"): ["2000"],
    ("--views", "M"): ["4"],             # M views per step
    ("--resolution-scale", "s"): ["2"],
    ("--voxel-size", "V"): ["0.05"],     # the anchor voxel edge
    ("--stages", "F:M:STEPS,..."): ["4:4:1000,2:2:1000,1:1:1000"],
    ("--scenes", "S..."): ["scenes/a", "scenes/b"],
}
PLACEHOLDER = re.compile(r"^(?:[A-Z][A-Z0-9_]*(?:\.\.\.)?|<[^>]*>|.*\.\.\..*|[a-z])$")
MAX_VARIANTS = 64
MIN_FOUND = 80  # the docs hold ~120 such lines: fewer found means the extraction broke
COMMAND_START = re.compile(r"^\s*(?:\$\s+)?(?:[A-Za-z_][A-Za-z0-9_]*=\S*\s+)*(?:python[0-9.]*|torchrun)\s")
SCRIPT = re.compile(r"^(?:\./)?((?:examples|benchmarks)/[\w/.-]+\.py)$")


class _Parsed(Exception):
    def __init__(self, namespace):
        super().__init__("parsed")
        self.namespace = namespace


@dataclass
class Command:
    doc: str
    line: int
    text: str                    # the command as written (joined)
    script: str = ""
    fragment: bool = False       # a bare `SCRIPT --flags` span or a trailing `...`: some flags only
    variants: list = field(default_factory=list)   # argument lists to parse
    skip: str = ""               # reason the line is not checked


# ---------------------------------------------------------------------------------------------
# finding the commands

def _snippets(path: Path):
    """(line number, text, is a code line) of every code line (fenced, or one that starts with a
    command; continuations joined, `# comments` cut) and every inline code span of a paragraph
    (joined across its line breaks), in the file's order."""
    lines = path.read_text().splitlines()
    out, i, fenced, paragraph = [], 0, False, []

    def flush():
        if paragraph:
            text = "\n".join(t for _, t in paragraph)
            starts = [n for n, _ in paragraph]
            offsets = list(itertools.accumulate(len(t) + 1 for _, t in paragraph))
            for m in re.finditer(r"`([^`]+)`", text):
                k = sum(1 for o in offsets if o <= m.start())
                out.append((starts[k], " ".join(m.group(1).split()), False))
            paragraph.clear()

    while i < len(lines):
        raw, n = lines[i], i + 1
        if raw.lstrip().startswith("```"):
            flush()
            fenced = not fenced
            i += 1
            continue
        stripped = raw.strip()
        if fenced or COMMAND_START.match(raw) or SCRIPT.match(stripped.split(" ")[0]):
            flush()
            text = raw
            while text.rstrip().endswith("\\") and i + 1 < len(lines):
                i += 1
                text = text.rstrip()[:-1] + " " + lines[i].strip()
            out.append((n, re.sub(r"(^|\s)#.*$", "", text).strip(), True))
        elif not stripped:
            flush()
        else:
            paragraph.append((n, raw))
        i += 1
    flush()
    return out


def _substitute(text: str, env: dict) -> str:
    for _ in range(4):
        new = re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: env.get(m.group(1) or m.group(2), m.group(0)), text)
        if new == text:
            break
        text = new
    return text


def _split_commands(text: str) -> list:
    """A snippet cut at &&, ||, ; and a pipe (` | `) outside [...] groups."""
    parts, depth, cur, k = [], 0, "", 0
    while k < len(text):
        c = text[k]
        depth += (c == "[") - (c == "]")
        if depth == 0 and (text.startswith("&&", k) or text.startswith("||", k)):
            parts.append(cur)
            cur, k = "", k + 2
            continue
        if depth == 0 and (c == ";" or (c == "|" and text[k - 1:k] == " " and text[k + 1:k + 2] == " ")):
            parts.append(cur)  # a pipe has spaces around it; a|b is a choice word
            cur, k = "", k + 1
            continue
        cur += c
        k += 1
    return [p.strip() for p in parts + [cur] if p.strip()]


def _alternatives(text: str) -> list:
    """Variants of a command: each optional [...] group included (one variant per ` | `
    alternative in it) and each a|b|c choice word one value per variant."""
    pieces = []
    for piece in re.split(r"(\[[^\[\]]*\])", text):
        if piece.startswith("[") and piece[1:-1].strip().startswith("-"):
            pieces.append([alt.strip() for alt in piece[1:-1].split(" | ")])
        else:
            pieces.append([piece])
    variants = []
    for combo in itertools.product(*pieces):
        words = [w.split("|") if "|" in w and not w.startswith("-") else [w] for w in " ".join(combo).split()]
        variants.extend(" ".join(ws) for ws in itertools.product(*words))
    return variants


def _expand_word(word: str) -> list:
    """bash's brace expansion and globbing (in the repository; kept when nothing matches)."""
    m = re.search(r"\{([^{}]*,[^{}]*)\}", word)
    if m:
        return [w for alt in m.group(1).split(",") for w in _expand_word(word[:m.start()] + alt + word[m.end():])]
    if any(c in word for c in "*?") and not word.startswith("-"):
        hits = sorted(glob.glob(word, root_dir=ROOT))
        return hits or [word]
    return [word]


def _is_flag(token: str) -> bool:
    return re.match(r"^--?[A-Za-z]", token) is not None


def _resolve_args(tokens: list) -> tuple:
    """(arguments, reason): placeholders replaced by PLACEHOLDERS; reason set for one that is not
    documented there (and not a path's)."""
    out, flag = [], None
    for tok in tokens:
        if _is_flag(tok):
            flag = tok.split("=")[0]
            out.append(tok)
            continue
        if (flag, tok) in PLACEHOLDERS:
            out.extend(PLACEHOLDERS[(flag, tok)])
            continue
        if flag in PATH_FLAGS:
            out.append(tok)
            continue
        if PLACEHOLDER.match(tok) or "$" in tok:
            return out, f"placeholder {tok!r} after {flag or 'the script'} is not one PLACEHOLDERS documents"
        out.append(tok)
    return out, ""


def find_commands() -> list:
    commands = []
    for doc in DOC_FILES:
        rel, env, last = doc.relative_to(ROOT).as_posix(), {}, {}
        for line, text, code in _snippets(doc):
            if code:
                for m in re.finditer(r"(?:^|;|&&|\s)(\w+)=(\"[^\"]*\"|'[^']*'|\S+)", text):
                    value = m.group(2).strip("\"'")
                    if not value.startswith("$("):  # a command's output: left unresolved
                        env[m.group(1)] = _substitute(value, env)
                for m in re.finditer(r"\bfor\s+(\w+)\s+in\s+(\S+)", text):
                    env[m.group(1)] = m.group(2)
            for part in _split_commands(text):
                cmd = _parse_command(rel, line, part, env, last)
                if cmd is not None:
                    commands.append(cmd)
    return commands


def _parse_command(doc: str, line: int, part: str, env: dict, last: dict):
    words = part.split()
    k = 0
    if k < len(words) and words[k] == "$":
        k += 1
    while k < len(words) and re.match(r"^[A-Za-z_]\w*=", words[k]):
        k += 1
    if k >= len(words):
        return None
    head = words[k]
    if re.match(r"^python[0-9.]*$", head):
        k += 1
        while k < len(words) and words[k].startswith("-") and words[k] not in ("-m", "-c"):
            k += 1
    elif head == "torchrun":
        k += 1
        while k < len(words) and not words[k].endswith(".py"):
            k += 1
    elif not SCRIPT.match(head):
        return None
    elif len(words) == k + 1:  # a bare path: a file named, not a command
        return None
    if k >= len(words) or not SCRIPT.match(words[k]):
        return None
    script = SCRIPT.match(words[k]).group(1)
    rest = " ".join(words[k + 1:])
    cmd = Command(doc, line, " ".join(words[k:]), script)
    if script not in SCRIPTS and (ROOT / script).exists():
        cmd.skip = "UNREGISTERED"
        return cmd
    cmd.fragment = head == words[k]
    rest = _substitute(rest, env)
    if re.search(r"<[^>]*>", rest):
        cmd.skip = f"placeholder {re.search(r'<[^>]*>', rest).group(0)!r} stands for any flags"
        return cmd
    if rest.split()[-1:] == ["..."] and len(rest.split()) > 1:  # the rest elided: check what is given
        rest, cmd.fragment = " ".join(rest.split()[:-1]), True
    if rest.split()[:1] == ["..."]:
        if script not in last:
            cmd.skip = "'...' with no earlier command of the same script in this file"
            return cmd
        rest = last[script] + " " + " ".join(rest.split()[1:])
    elif "..." not in rest.split():
        last[script] = rest
    variants = _alternatives(rest)
    if len(variants) > MAX_VARIANTS:
        cmd.skip = f"{len(variants)} variants"
        return cmd
    for variant in variants:
        try:
            tokens = shlex.split(variant)
        except ValueError as err:
            cmd.skip = f"shlex: {err}"
            return cmd
        tokens = [w for tok in tokens for w in _expand_word(tok)]
        args, why = _resolve_args(tokens)
        if why:
            cmd.skip, cmd.variants = why, []
            return cmd
        cmd.variants.append(args)
    return cmd


# ---------------------------------------------------------------------------------------------
# parsing

def _any_path(text: str) -> Path:
    """Stands in for scene_folder / checkpoint_file: the author's paths do not exist here."""
    return Path(text)


class _Parser:
    def __init__(self, monkeypatch):
        self.mp = monkeypatch
        self.modules = {}
        self.real_parse = argparse.ArgumentParser.parse_args

    def _load(self, script: str):
        if script not in self.modules:
            spec = importlib.util.spec_from_file_location("doc_cmd_" + Path(script).stem, ROOT / script)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            self.modules[script] = module
        return self.modules[script]

    def parse(self, script: str, argv: list) -> str:
        """'' when the script's parser accepts argv, else the error it gives."""
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                if SCRIPTS[script] == "parse_args":
                    with self.mp.context() as mp:  # argparse names the script in its message
                        mp.setattr(sys, "argv", [str(ROOT / script), *argv])
                        self._load(script).parse_args(list(argv))
                else:
                    self._run_main(script, argv)
        except _Parsed:
            return ""
        except SystemExit as exit_:
            if exit_.code in (0, None):
                return ""
            message = err.getvalue().strip().splitlines()
            text = message[-1] if message else str(exit_.code)
            return text
        except Exception as exc:  # noqa: BLE001 - reported with the doc line
            return f"{type(exc).__name__}: {exc}"
        return ""

    def _run_main(self, script: str, argv: list) -> None:
        stop_at = PARSES_BEFORE_STOP.get(script, 1)
        seen = [0]
        real = self.real_parse

        def parse_then_stop(parser, args=None, namespace=None):
            ns = real(parser, args, namespace)
            seen[0] += 1
            if seen[0] >= stop_at:
                raise _Parsed(ns)
            return ns

        path = ROOT / script
        with self.mp.context() as mp:
            mp.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
            mp.setattr(sys, "argv", [str(path), *argv])
            mp.syspath_prepend(str(path.parent))
            before = set(sys.modules)
            try:
                runpy.run_path(str(path), run_name="__main__")
            finally:  # the scripts' sibling modules (common, gaussian_model) are not kept
                for name in set(sys.modules) - before:
                    f = getattr(sys.modules[name], "__file__", None) or ""
                    if f.startswith(str(ROOT / "examples")) or f.startswith(str(ROOT / "benchmarks")):
                        del sys.modules[name]
        raise AssertionError(f"{script} ran to its end without parsing its arguments")


def test_every_documented_command_parses(monkeypatch):
    monkeypatch.setattr(cli, "scene_folder", _any_path)
    monkeypatch.setattr(cli, "checkpoint_file", _any_path)
    parser = _Parser(monkeypatch)

    commands = find_commands()
    failures, skipped, checked = [], [], 0
    for cmd in commands:
        where = f"{cmd.doc}:{cmd.line}"
        if cmd.skip == "UNREGISTERED":
            failures.append(f"{where}: {cmd.text}\n    {cmd.script} is not in SCRIPTS of {Path(__file__).name}")
            continue
        if not (ROOT / cmd.script).exists():
            failures.append(f"{where}: {cmd.text}\n    {cmd.script} does not exist")
            continue
        if cmd.script in NOT_PARSED:
            skipped.append((where, cmd.text, NOT_PARSED[cmd.script]))
            continue
        needed = next((pkg for prefix, pkg in NEEDS.items() if cmd.script.startswith(prefix)), None)
        if needed and importlib.util.find_spec(needed) is None:
            skipped.append((where, cmd.text, f"{needed} is not installed"))
            continue
        if cmd.skip:
            skipped.append((where, cmd.text, cmd.skip))
            continue
        checked += 1
        for argv in cmd.variants:
            error = parser.parse(cmd.script, argv)
            if error and cmd.fragment and "the following arguments are required" in error:
                error = ""  # a fragment names some of the flags; the required ones may be elsewhere
            if error:
                failures.append(f"{where}: {cmd.script} {shlex.join(argv)}\n    {error}")

    found = len(commands)
    print(f"\n{found} documented commands found ({sum(c.fragment for c in commands)} of them fragments), {checked} "
          f"checked ({sum(len(c.variants) for c in commands)} argument lists parsed), {len(skipped)} skipped")
    for where, text, why in skipped:
        print(f"  skipped {where}: {text}\n      ({why})")
    assert found >= MIN_FOUND, f"only {found} commands found in the docs: is the extraction broken?"
    assert checked >= 0.8 * found, f"only {checked} of {found} commands checked; skipped: {skipped}"
    assert not failures, (f"{len(failures)} documented command line(s) that the script's parser refuses:\n"
                          + "\n".join(failures))


if __name__ == "__main__":  # the commands found, for a look at the extraction
    for c in find_commands():
        print(f"{c.doc}:{c.line}: [{c.script}] {c.skip or ''}")
        for v in c.variants:
            print("     ", shlex.join(v))
