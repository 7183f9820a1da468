"""The fuzz pass over the command line (bench/fuzz_cli.py), reduced: every verb, malformed values for every
option, damaged input files; no traceback, no exit 0 after an error or on a value that must be refused.

In-process (click's CliRunner), one malformed value per option that must be refused plus one other, and a
few damaged files per kind of input. Full pass (every value, more mutants), by hand:
``python -m bench.fuzz_cli``.
"""
import random

import click

from bench import fuzz_cli


def test_the_cases_cover_every_verb_and_every_option(tmp_path):
    from dic.cli import SUBCOMMANDS

    paths = {k: str(tmp_path / k) for k in ("ref", "cur", "ref_png", "camera", "rig", "target", "scene", "results")}
    cases = fuzz_cli.cases(paths, 1, random.Random(0))
    verbs = {c["verb"].split()[0] for c in cases}
    assert verbs == set(SUBCOMMANDS)
    for verb in fuzz_cli.baselines(paths):
        cmd = fuzz_cli._command(verb)
        options = [p for p in cmd.params if isinstance(p, click.Option) and not p.is_flag and p.name != "help"]
        tried = {c["what"].split("=")[0] for c in cases if c["verb"] == verb}
        assert {p.opts[-1] for p in options} <= tried, verb
        assert any(c["must_refuse"] for c in cases if c["verb"] == verb)


def test_the_case_check_catches_what_it_must():
    """run_case flags a traceback, an exit 0 after an error, and an accepted value that must be refused."""
    assert "accepted a value" in fuzz_cli.run_case({"args": ["--version"], "must_refuse": True}, [0])
    assert fuzz_cli.run_case({"args": ["--version"], "must_refuse": False}, [0]) is None
    assert fuzz_cli.run_case({"args": ["track", "--subset", "abc"], "must_refuse": True}, [0]) is None


def test_fuzz_cli_reduced():
    res = fuzz_cli.run(per_option=2, mutants=3, seed=2, verbose=False)
    problems = "\n".join(f"{f['verb']} {f['what']}: {f['problem'][:500]}" for f in res["failures"])
    assert not res["failures"], problems
    assert res["cases"] > 250 and len(res["by_verb"]) >= 17
