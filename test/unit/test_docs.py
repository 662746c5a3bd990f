"""The documentation is current and its examples are valid: every relative link resolves, the
parameter table is the one the specs render, and every `art-guidance` command that the README,
docs/ and the `--help` texts give as an example parses with the real command line (a usage error
fails here; `test_cli.py` runs the node example for real, as a server with a timeout)."""
from __future__ import annotations

import argparse
import os
import re
import shlex
from pathlib import Path

import pytest

from art_guidance.cli import build_parser
from art_guidance.config import node_parameter_defaults
from art_guidance.ros.parameters import TABLE_BEGIN, TABLE_END, parameter_table

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _doc_commands() -> list[tuple[str, str]]:
    """(page, command) for every `art-guidance ...` line of a fenced code block."""
    out = []
    for page in PAGES:
        for block in re.findall(r"```[a-z]*\n(.*?)```", page.read_text(), flags=re.S):
            text = re.sub(r"\\\n\s*", " ", block)
            shell = dict(re.findall(r'^([A-Z_]+)="([^"]*)"$', text, flags=re.M))
            for line in text.splitlines():
                line = line.split("  #")[0].strip()
                for name, value in shell.items():
                    line = line.replace(f"${name}", value)
                m = re.match(r"(?:\.venv/bin/)?art-guidance (.*)", line)
                if m and not re.search(r"[\[|]", m.group(1)):  # a synopsis is no example
                    out.append((page.name, m.group(1)))
    return out


def _help_texts(parser: argparse.ArgumentParser, name: str = "art-guidance") -> list:
    texts = [(name, parser.description or ""), (name, parser.epilog or "")]
    for action in parser._actions:
        texts.append((name, action.help or ""))
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                texts += _help_texts(sub, f"{name} {sub_name}")
    return texts


def _help_commands() -> list[tuple[str, str]]:
    out = []
    for where, text in _help_texts(build_parser()):
        text = re.sub(r"\\\n\s*", " ", text)
        for m in re.finditer(r"art-guidance ([a-z][^`\n]*)", text):
            command = m.group(1).split("  (")[0].rstrip(" .;)")
            if "{" in command or "..." in command or " " not in command:
                continue  # a template or a bare command name in prose, not an example
            out.append((where, command))
    return out


EXAMPLES = _doc_commands() + _help_commands()


def test_examples_were_found():
    pages = {p for p, _ in EXAMPLES}
    assert {"README.md", "fault_tolerance.md", "visualization.md"} <= pages
    assert any(w.startswith("art-guidance evaluate") for w, _ in EXAMPLES)
    assert len(EXAMPLES) >= 20


@pytest.mark.parametrize("where, command", EXAMPLES, ids=[f"{w}: {c}"[:80] for w, c in EXAMPLES])
def test_example_command_parses(where, command, capsys):
    argv = shlex.split(command)
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{where}: `art-guidance {command}` is a usage error ({exc.code}): "
                    f"{capsys.readouterr().err.strip()}")
    assert callable(args.func)


def test_relative_links_resolve():
    broken = []
    for page in PAGES:
        for m in re.finditer(r"\]\(([^)#\s]+)(#[^)]*)?\)", page.read_text()):
            target = m.group(1)
            if not target.startswith(("http://", "https://", "mailto:")) \
                    and not (page.parent / target).exists():
                broken.append(f"{page.name}: {target}")
    assert broken == []


def test_parameter_table_is_rendered_from_the_specs():
    text = (ROOT / "docs" / "node.md").read_text()
    table = text[text.index(TABLE_BEGIN) + len(TABLE_BEGIN):text.index(TABLE_END)].strip("\n")
    assert table + "\n" == parameter_table(node_parameter_defaults()), \
        "regenerate with art_guidance.ros.parameters.parameter_table"


@pytest.mark.slow
def test_every_example_runs_without_a_usage_error(tmp_path, ros_env):
    """Every distinct example command, run for real in an empty directory (its own ROS 2
    domain): it may fail on missing data (exit 2 with a JSON error) or still be running after
    two seconds (a server, a long job: then it is killed), but argparse must never reject
    it (its "usage:" line and exit 2; argparse answers before a command's work begins, so a
    longer run checks nothing more). Ray examples are parsed only (a Ray instance outlives a
    killed driver). The commands are forked from one process that has imported the package
    and its dependencies once (helpers/cli_runs.py), six at a time: most are killed at their
    timeout, which is wall-clock time, so running more at once spends less of it."""
    from helpers.cli_runs import run_briefly

    commands = sorted({c for _, c in EXAMPLES if "--engine ray" not in c})
    env = dict(ros_env, PYTHONPATH=os.pathsep.join([str(ROOT), ros_env.get("PYTHONPATH", "")]))
    jobs = []
    for k, command in enumerate(commands):
        cwd = tmp_path / f"run{k}"
        cwd.mkdir()
        jobs.append((command, cwd))

    outcomes = [(c, *outcome) for c, outcome in zip(commands, run_briefly(jobs, env, 2.0, 6))]
    bad = [f"{c}: {err.strip()[-300:]}" for c, code, err in outcomes
           if code == 2 and "usage:" in err]
    assert bad == []
    assert len(outcomes) == len(commands) >= 30


_MACHINE_PATH = re.compile(r"(?<![\w.])/(?:work|home|root|tmp|Users|mnt|opt)/[\w.-]")


def test_committed_results_and_docs_hold_no_machine_paths():
    """Results, model provenance and docs name paths relative to the checkout (a recorded
    /work/... or /tmp/... says nothing on another machine and leaks the one it ran on)."""
    roots = [ROOT / "benchmarks" / "results", ROOT / "docs", ROOT / "art_guidance" / "models",
             ROOT / "config"]
    files = [ROOT / "README.md"] + [p for r in roots for p in sorted(r.rglob("*"))
                                    if p.suffix in (".json", ".md", ".yaml", ".txt")]
    found = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in files
             for m in _MACHINE_PATH.finditer(p.read_text(errors="replace"))]
    assert not found, found[:10]
