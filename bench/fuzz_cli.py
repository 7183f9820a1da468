"""Fuzz pass over the command line (issue 24): every verb, malformed values for every option, damaged files.

Run from the repository root::

    .venv/bin/python -m bench.fuzz_cli                    # full: every malformed value for every option
    .venv/bin/python -m bench.fuzz_cli --values 2         # reduced (tests/project/test_cli_fuzz.py): 2 values per option
    .venv/bin/python -m bench.fuzz_cli --mutants 20       # more damaged files per input kind

The cases run in-process through click's ``CliRunner`` (``specula <verb> ...``) in a scratch folder
that also holds the inputs: two 48 x 64 px speckle images, a 2-D result file of ``specula track``, a
stereo rig of the images' size, a camera file, a phase target and a small virtual-lab scene. Each
verb has a cheap valid command line; a case replaces one option's value (or one argument) by a
malformed one, chosen by the option's type (numbers: empty, blank, NaN, infinities, text, negative,
zero, 1e300, 2**70; choices: empty, nonsense; paths and text: empty, blank, a missing folder, control
characters, 300 characters, "1e300,1e300"), or one input file by a damaged copy (the mutations of
:mod:`bench.fuzz_inputs`: byte flips, truncation, header edits; result files truncated or with
flipped bytes with ``--flip-results``). Verbs that would calibrate or render a session for minutes get only the values that
must be refused before any work.

A case fails when

* an exception other than click's exit escapes (a traceback), or the output shows one;
* it exits 0 after an ``Error:`` line;
* a value that must be refused (empty or blank text, NaN or text for a number, a nonsense choice)
  exits 0.

Everything else (a refusal with exit 1 or 2 and one message, or a run that accepts a value it
can use) passes. Prints one line per failure and a summary; exit status 1 when any case failed.
"""
from __future__ import annotations

import argparse
import os
import random
import shutil
import sys
import tempfile
import time
import traceback

import click
import numpy as np

#: verbs whose valid command line is cheap enough to run when a malformed value is accepted
CHEAP = {"track", "stereo", "strain", "crack", "extensometer", "history", "profile", "export", "animate", "report", "speckle",
         "target fringes",
         "target checkerboard", "target circles", "lab render", "lab paper-rig"}
INT_VALUES = ["", " ", "nan", "abc", "-1", "0", "1e300", str(2 ** 70), "3.5"]
FLOAT_VALUES = ["", " ", "nan", "inf", "-inf", "abc", "-1", "0", "1e300", "-1e300"]
CHOICE_VALUES = ["", "nonsense"]
TEXT_VALUES = ["", " ", "/nonexistent/folder/x", "\x01\x02", "a" * 300, "1e300,1e300", "-1", "nan"]
MUST_REFUSE_TEXT = {"", " "}
MUST_REFUSE_NUMBER = {"", " ", "nan", "abc"}


def build_inputs(folder: str) -> dict:
    """Write the inputs into ``folder``; returns their paths by name."""
    from calibration.camera import Camera
    from calibration.stereo import StereoRig
    from calibration.targets import PhaseTarget
    from dic.cli import main
    from dic.io import write_image
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((48, 64), (0.3, -0.2), seed=11)
    paths = {"ref": os.path.join(folder, "ref.tif"), "cur": os.path.join(folder, "cur.tif")}
    write_image(paths["ref"], ref, bits=8)
    write_image(paths["cur"], cur, bits=8)
    paths["ref_png"] = str(write_image(os.path.join(folder, "ref.png"), ref, bits=8))
    cam = Camera(K=[[80.0, 0, 32.0], [0, 80.0, 24.0], [0, 0, 1]], size=(64, 48), name="left")
    paths["camera"] = os.path.join(folder, "camera.json")
    cam.save(paths["camera"])
    paths["rig"] = os.path.join(folder, "rig.json")
    StereoRig(cam, cam, np.eye(3), [100.0, 0, 0]).save(paths["rig"])
    paths["target"] = os.path.join(folder, "target.json")
    PhaseTarget(screen=(320, 240), grid=(4, 2), pitch=60, steps=3).save_json(paths["target"])
    paths["scene"] = os.path.join(folder, "scene.toml")
    with open(paths["scene"], "w") as fh:
        fh.write(SCENE)
    paths["results"] = os.path.join(folder, "results.h5")
    res = _runner().invoke(main, ["track", paths["ref"], paths["cur"], "-o", paths["results"], "--step", "12",
                                  "--device", "cpu", "-q"])
    if res.exit_code != 0:
        raise RuntimeError(f"cannot build the result file: {res.output}")
    return paths


SCENE = """background = 0.1

[[camera]]
name = "cam"
size = [16, 12]
pixel_pitch_mm = 0.08
focal_length_mm = 12.0
f_number = inf
focus_distance_mm = 1000.0
position = [0.0, 0.0, 0.0]
look_at = [0.0, 0.0, 1000.0]

[[plane]]
size = [200.0, 200.0]
center = [0.0, 0.0, 1000.0]
normal = [0.0, 0.0, -1.0]
speckle = { radius = 3.0, density = 0.4, seed = 2 }
"""


def baselines(p: dict) -> dict[str, list[str]]:
    """A valid, cheap command line per verb; ``{out}`` is replaced by a fresh output name per case."""
    return {
        "track": ["track", p["ref"], p["cur"], "-o", "{out}.h5", "--step", "12", "--device", "cpu", "-q"],
        "stereo": ["stereo", "--rig", p["rig"], p["ref"], p["cur"], p["ref"], p["cur"], "-o", "{out}.h5", "--step",
                   "16", "--device", "cpu", "-q", "--allow-empty"],
        "strain": ["strain", p["results"], "--window", "3", "-o", "{out}.h5", "-q"],
        "extensometer": ["extensometer", p["results"], "--from", "15,20", "--to", "45,20"],
        "history": ["history", p["results"], "--point", "30,24"],
        "profile": ["profile", p["results"], "--from", "15,24", "--to", "45,24"],
        "export": ["export", p["results"], "-f", "csv", "-o", "{out}"],
        "animate": ["animate", p["results"], "-Q", "u", "-o", "{out}.gif", "--dpi", "20", "-q"],
        "report": ["report", p["results"], "-o", "{out}.html", "-Q", "u", "--map-width", "64", "-q"],
        "repair": ["repair", p["results"]],
        "crack": ["crack", p["results"], "--crack", "30,-5,30,60", "--frame", "1", "-o", "{out}.csv", "-q"],
        "speckle": ["speckle", p["ref"], "--step", "16", "--device", "cpu"],
        "target fringes": ["target", "fringes", "-o", "{out}", "--screen", "320x240", "--grid", "4x2", "--pitch", "60",
                           "--steps", "3"],
        "target checkerboard": ["target", "checkerboard", "-o", "{out}", "--screen", "320x240", "--corners", "4x3",
                                "--square", "40"],
        "target show": ["target", "show", os.path.dirname(p["target"]) or ".", "--interval", "1"],  # refusals only
        "target circles": ["target", "circles", "-o", "{out}", "--screen", "320x240", "--grid", "4x3", "--pitch", "60"],
        "lab render": ["lab", "render", p["scene"], "-o", "{out}", "--samples", "1", "--device", "cpu"],
        "lab paper-rig": ["lab", "paper-rig", "-o", "{out}.toml", "--scale", "0.05", "--tilt", "none"],
        "lab session": ["lab", "session", "{out}", "--scale", "0.05", "--samples", "1"],
        "calibrate intrinsics": ["calibrate", "intrinsics", p["ref"], p["cur"], p["ref_png"], "--target", p["target"],
                                 "-o", "{out}.json", "--device", "cpu"],
        "calibrate mirror": ["calibrate", "mirror", p["ref"], p["cur"], p["ref_png"], "--camera", p["camera"],
                             "--target", p["target"], "-o", "{out}.json", "--device", "cpu"],
        "calibrate stereo": ["calibrate", "stereo", "--left", p["camera"], "--right", p["camera"], "-o", "{out}.json"],
    }


def _runner():
    from click.testing import CliRunner

    return CliRunner()


def _command(verb: str) -> click.Command:
    from dic.cli import main

    ctx = click.Context(main)
    cmd = main
    for word in verb.split():
        cmd = cmd.get_command(ctx, word)
    return cmd


def _values(param: click.Parameter) -> tuple[list[str], set[str]]:
    """The malformed values to try for a parameter, and those of them it must refuse."""
    t = param.type
    inner = getattr(t, "inner", t)
    if isinstance(inner, click.Choice):
        return CHOICE_VALUES, set(CHOICE_VALUES)
    if isinstance(inner, (click.types.IntParamType, click.IntRange)):
        return INT_VALUES, MUST_REFUSE_NUMBER
    if isinstance(inner, (click.types.FloatParamType, click.FloatRange)):
        return FLOAT_VALUES, MUST_REFUSE_NUMBER
    if isinstance(inner, click.Tuple):
        return FLOAT_VALUES, MUST_REFUSE_NUMBER
    return TEXT_VALUES, MUST_REFUSE_TEXT


def _with_value(base: list[str], param: click.Parameter, value: str) -> list[str] | None:
    """``base`` with the option ``param`` set to ``value`` (replacing its value there, else appended)."""
    if not isinstance(param, click.Option) or param.is_flag or param.count:
        return None
    names = [n for n in param.opts + param.secondary_opts if n.startswith("--")] or param.opts
    n = max(1, param.nargs)
    out = list(base)
    for name in param.opts:
        if name in out:
            i = out.index(name)
            out[i + 1:i + 1 + n] = [value] * n
            return out
    return out + [names[0]] + [value] * n


def cases(paths: dict, per_option: int | None, rng: random.Random) -> list[dict]:
    """Every (verb, option, value) case: all malformed values, or ``per_option`` of them per option (one that
    must be refused among them)."""
    out = []
    for verb, base in baselines(paths).items():
        cmd = _command(verb)
        for param in cmd.params:
            if param.name in ("help",) or not isinstance(param, click.Option):
                continue
            values, must = _values(param)
            if verb not in CHEAP:
                values = [v for v in values if v in must]
            if per_option is not None and len(values) > per_option:
                refused = [v for v in values if v in must]
                others = [v for v in values if v not in must]
                pick = [rng.choice(refused)] if refused else []
                pick += rng.sample(others, min(len(others), per_option - len(pick))) if others else []
                values = pick
            for value in values:
                args = _with_value(base, param, value)
                if args is not None:
                    out.append({"verb": verb, "what": f"{param.opts[-1]}={value!r:.40}", "args": args,
                                "must_refuse": value in must})
        out.append({"verb": verb, "what": "unknown option", "args": base + ["--no-such-option"], "must_refuse": True})
    return out


def damaged_cases(paths: dict, folder: str, mutants: int, rng: random.Random) -> list[dict]:
    """The cheap verbs with one input file replaced by a damaged copy (``mutants`` per kind of input)."""
    from bench.fuzz_inputs import mutate_bytes, mutate_image, mutate_json

    base = baselines(paths)
    kinds = [("ref", ["track", "speckle"], lambda d: mutate_image(d, rng, "ref.tif")),
             ("ref_png", ["speckle"], lambda d: mutate_image(d, rng, "ref.png")),
             ("rig", ["stereo"], lambda d: mutate_json(d, rng)),
             ("scene", ["lab render"], lambda d: mutate_bytes(d, rng)),
             ("results", ["strain", "history", "profile", "export", "extensometer", "animate", "report", "crack"],
              lambda d: _damage_h5(d, rng))]
    out = []
    for key, verbs, mutate in kinds:
        data = open(paths[key], "rb").read()
        suffix = os.path.splitext(paths[key])[1]
        for k in range(mutants):
            try:
                damaged, note = mutate(data)
            except (ValueError, RecursionError):
                damaged, note = mutate_bytes(data, rng)
            path = os.path.join(folder, f"damaged_{key}_{k}{suffix}")
            with open(path, "wb") as fh:
                fh.write(damaged)
            verb = verbs[k % len(verbs)]
            if key == "ref_png":
                args = [a if a != paths["ref"] else path for a in base[verb]]
            else:
                args = [a if a != paths[key] else path for a in base[verb]]
            out.append({"verb": verb, "what": f"damaged {key}: {note:.60}", "args": args, "must_refuse": False})
    return out


FLIP_RESULTS = False  # --flip-results: also flip bytes of result files (see main)


def _damage_h5(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A result file cut short, or (FLIP_RESULTS) with bytes flipped."""
    if not FLIP_RESULTS or rng.random() < 0.5:
        n = rng.randrange(0, len(data))
        return data[:n], f"truncated to {n} bytes"
    out = bytearray(data)
    at = [rng.randrange(0, len(data)) for _ in range(rng.choice([1, 4, 32]))]
    for i in at:
        out[i] ^= 1 << rng.randrange(8)
    return bytes(out), f"{len(at)} byte(s) flipped"


def run_case(case: dict, counter: list) -> str | None:
    """Run one case; the failure in words, or None."""
    from dic.cli import main

    counter[0] += 1
    args = [a.replace("{out}", f"out{counter[0]}") for a in case["args"]]
    res = _runner().invoke(main, args)
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        tb = "".join(traceback.format_exception(type(res.exception), res.exception, res.exception.__traceback__))
        return f"traceback: {type(res.exception).__name__}: {res.exception}"[:300] + " | " + tb[-500:]
    if "Traceback (most recent call last)" in res.output:
        return "a traceback in the output: " + res.output[-400:]
    if res.exit_code == 0 and "Error:" in res.output:
        return "exit 0 after an error: " + res.output[-300:]
    if res.exit_code == 0 and case["must_refuse"]:
        return "accepted a value that must be refused (exit 0): " + res.output[-300:]
    return None


def run(per_option: int | None = None, mutants: int = 6, seed: int = 0, verbose: bool = True) -> dict:
    """The pass; returns counts, failures and the time."""
    import logging
    import warnings

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    rng = random.Random(seed)
    folder = tempfile.mkdtemp(prefix="specula_fuzz_cli_")
    here = os.getcwd()
    t0 = time.perf_counter()
    failures, by_verb = [], {}
    try:
        os.chdir(folder)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            paths = build_inputs(folder)
            todo = cases(paths, per_option, rng) + damaged_cases(paths, folder, mutants, rng)
            counter = [0]
            for case in todo:
                t_case = time.perf_counter()
                problem = run_case(case, counter)
                c = by_verb.setdefault(case["verb"], {"cases": 0, "failures": 0, "seconds": 0.0})
                c["cases"] += 1
                c["seconds"] += time.perf_counter() - t_case
                if problem:
                    c["failures"] += 1
                    failures.append({**case, "problem": problem})
                    if verbose:
                        print(f"FAIL {case['verb']} {case['what']}: {problem}", file=sys.stderr)
    finally:
        os.chdir(here)
        shutil.rmtree(folder, ignore_errors=True)
    return {"cases": sum(c["cases"] for c in by_verb.values()), "by_verb": by_verb, "failures": failures,
            "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--values", type=int, default=None, help="malformed values per option (default: all)")
    ap.add_argument("--mutants", type=int, default=6, help="damaged files per kind of input (default 6)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the choices and mutations")
    ap.add_argument("--flip-results", action="store_true",
                    help="also flip bytes inside result files (HDF5 metadata damage can still end in h5py's own "
                         "KeyError/RuntimeError: the result-file readers' part of issue 24, not this pass's)")
    args = ap.parse_args(argv)
    global FLIP_RESULTS
    FLIP_RESULTS = args.flip_results
    res = run(args.values, args.mutants, args.seed)
    print(f"{'verb':22s} {'cases':>6s} {'FAIL':>5s} {'seconds':>8s}")
    for verb, c in res["by_verb"].items():
        print(f"{verb:22s} {c['cases']:6d} {c['failures']:5d} {c['seconds']:8.1f}")
    print(f"{'total':22s} {res['cases']:6d} {len(res['failures']):5d}   in {res['seconds']:.1f} s")
    return 1 if res["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
