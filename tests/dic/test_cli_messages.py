"""CLI messages of issue 25 (items 7 and 9): Ctrl-C, the settings-mismatch error, valid counts over the region,
a closed pipe, option help, reprs and the messages of wrong inputs."""
import numpy as np
import pytest
from click.testing import CliRunner
from test_cli_track import FakeTracker, fake, images  # noqa: F401 - the fixtures

from dic.cli import main
from dic.store import read_results


class InterruptedTracker(FakeTracker):
    """Ctrl-C (KeyboardInterrupt) while frame 2 is tracked: frame 1 is finished and written."""

    def track(self, current, guess=None):
        if FakeTracker.calls == 1:
            raise KeyboardInterrupt
        return super().track(current, guess)


def test_ctrl_c_in_track_says_what_is_saved_and_how_to_resume(images, tmp_path, monkeypatch):  # noqa: F811
    import dic.commands.track as cmd

    FakeTracker.calls = 0
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: InterruptedTracker(ref, **kw))
    out = tmp_path / "res.h5"
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 130, r.output
    assert f"1 frame saved in {out}; run the same command again to resume" in r.output
    assert "Aborted!" not in r.output
    assert read_results(out).indices == [1]
    # the same command resumes: frame 1 is skipped, frame 2 computed
    FakeTracker.calls = 0
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: FakeTracker(ref, **kw))
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "1 frame(s) were already in" in r.output and read_results(out).indices == [1, 2]


def test_ctrl_c_before_any_frame_says_none_was_saved(images, tmp_path, monkeypatch):  # noqa: F811
    import dic.commands.track as cmd

    def stop(ref, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd, "_make_tracker", stop)
    out = tmp_path / "res.h5"
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 130 and f"no frame was saved in {out} yet" in r.output, r.output


def test_every_refusal_to_resume_names_overwrite(images, tmp_path, fake):  # noqa: F811 - fixtures
    """Another reference image, other settings, another image size, not a Specula file: each refusal names
    --overwrite."""
    out = tmp_path / "res.h5"
    assert CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"]).exit_code == 0
    for args in ([images[1], images[0], images[2]], [*images, "--step", "6"]):
        args = [*args, "--step", "8"] if "--step" not in args else args
        r = CliRunner().invoke(main, ["track", *args, "-o", str(out)])
        assert r.exit_code == 1 and "--overwrite" in r.output, r.output
        assert "Traceback" not in r.output
    import h5py

    from dic.store import ResultWriter

    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5.attrs["format"] = "someone else's"
    with pytest.raises(ValueError, match="--overwrite"):  # not a Specula file
        ResultWriter(other, settings={}, mode="resume").close()
    with pytest.raises(ValueError, match=r"reference of shape \(96, 112\), not \(96, 128\).*--overwrite"):
        ResultWriter(out, reference_shape=(96, 128), settings={}, mode="resume").close()  # no digest to compare


def test_a_reader_that_closes_the_pipe_early_gets_no_error_message(tmp_path):
    """``specula <command> | head -1``: the command's output stops quietly, without "Error: Broken pipe"."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "chatty.py").write_text(
        "import click\n\n@click.command()\ndef chatty():\n    for k in range(200000):\n        click.echo(f'line {k}')\n")
    script = ("import sys; sys.path.insert(0, sys.argv[1]); import dic.cli as cli; "
              "cli.SUBCOMMANDS['chatty'] = ('chatty:chatty', 'prints many lines'); sys.argv[1:] = ['chatty']; cli.main()")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[2]), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    assert proc.stdout.readline() == b"line 0\n"
    proc.stdout.close()  # what head does after its first line
    err = proc.stderr.read().decode()
    proc.wait(timeout=60)
    assert "Broken pipe" not in err and "Traceback" not in err and "Error" not in err, err
    assert proc.returncode == 1


def test_stereo_help_names_only_its_own_options():
    """``specula stereo --help`` named --search, an option of ``specula track`` only."""
    import re

    from dic.commands.stereo import stereo

    stereo_help = CliRunner().invoke(main, ["stereo", "--help"], terminal_width=200)
    assert stereo_help.exit_code == 0
    own = {o for p in stereo.params for o in (*p.opts, *getattr(p, "secondary_opts", ()))} | {"--help"}
    text = stereo_help.output.replace("-\n  ", "-")  # an option name broken at the end of a line
    named = set(re.findall(r"(?<![\w-])--[a-z][a-z-]+[a-z]", text))
    assert named <= own, named - own
    assert "--search" in CliRunner().invoke(main, ["track", "--help"], terminal_width=200).output


def test_strain_refuses_both_window_units(tmp_path):
    """``--px --grid-points`` took the last one given; now they are refused together (before reading the file)."""
    for units in (["--px", "--grid-points"], ["--grid-points", "--px"]):
        r = CliRunner().invoke(main, ["strain", str(tmp_path / "res.h5"), "--window", "9", *units])
        assert r.exit_code == 2 and "--px and --grid-points exclude each other" in r.output, r.output


def _stereo_scene(tmp_path):
    """A rig file and one left/right pair of the stereo sequence tests' lab scene (a speckled plane; no motion)."""
    from test_stereo_sequence import _cameras

    from dic.io import write_image
    from dic.lab import Scene, SpecklePlane, render, stereo_rig
    from dic.synth import make_speckle

    cams = _cameras()
    speckle = make_speckle(region=(-5, -5, 305, 255), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(300.0, 250.0), speckle=speckle)
    scene = Scene(cameras=cams, planes=[plane])
    left, right = cams
    stereo_rig(left, right).save(tmp_path / "rig.json")
    return [str(write_image(tmp_path / f"{side}.png", render(scene, i, samples=4, seed=i)))
            for i, side in enumerate(("L", "R"))]


def test_stereo_summary_counts_valid_points_over_the_region(tmp_path):
    """``state 0: 1292/8614 valid points`` divided by the whole grid, the points outside --roi included; the count is
    now over the points computed in the region (status not NOT_COMPUTED), for the summary and the printed line."""
    from test_stereo_sequence import STEP

    from dic.field3d import StereoStatus
    from dic.store import read_stereo

    paths = _stereo_scene(tmp_path)
    out = tmp_path / "roi.h5"
    r = CliRunner().invoke(main, ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "--step", str(STEP),
                                  "--roi", "100", "80", "220", "160", "-o", str(out)])
    assert r.exit_code == 0, r.output
    f = read_stereo(out).fields[0]
    computed = f.status != StereoStatus.NOT_COMPUTED
    n_valid, n_region = int(np.count_nonzero(f.valid)), int(np.count_nonzero(computed))
    assert 0 < n_region < len(f) // 2  # the region holds a minority of the grid
    assert f"state 0: {n_valid}/{n_region} valid points in the region" in r.output


def test_short_reprs_of_result_files(tmp_path):
    """ResultFrames and ResultReader had object reprs; a library-written file's repr names its order too, and the
    sequence summary stays one short line (no dict per frame)."""
    from dic.sequence import track_sequence
    from dic.store import ResultFrames, ResultReader
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((96, 112), (0.4, -0.3), seed=21)
    out = tmp_path / "lib.h5"
    summary = track_sequence(ref, [cur] * 3, out, subset=21, step=8, order=2, progress=False)
    text = repr(summary)
    assert text.startswith("<SequenceSummary: 3 computed (1..3)") and "{" not in text and len(text) < 200, text
    assert "order 2" in repr(read_results(out))
    expected = f"'{out}': 2-D DIC, frames 3 (1..3), order 2, subset 21, step 8>"
    with ResultReader(out) as reader:
        assert repr(reader) == "<ResultReader " + expected
    assert repr(reader) == f"<ResultReader '{out}': 2-D DIC, closed>"
    with ResultFrames(out) as frames:
        assert repr(frames) == "<ResultFrames " + expected
    assert repr(ResultFrames(read_results(out))) == "<ResultFrames " + expected


def test_dataframe_keeps_each_image_path_once(images, tmp_path, fake):  # noqa: F811 - fixtures
    """The per-row ``path`` string took 113 of 246 MB of a long file's table: it is a categorical now (one
    code per row, each path once), with the same values."""
    out = tmp_path / "res.h5"
    assert CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"]).exit_code == 0
    df = read_results(out).to_dataframe()
    assert df["path"].dtype == "category"
    assert list(df["path"].cat.categories) == sorted(images[1:])
    assert (df.xs(2, level="frame")["path"] == images[2]).all()
    assert df["path"].memory_usage(deep=True, index=False) < 2 * len(df) + 1000  # int8 codes + the two texts


@pytest.mark.parametrize("left_name, right_name", [("Left_{k}.png", "Right_{k}.png"), ("img_{k}_L.tif", "img_{k}_R.tif"),
                                                   ("cam0_{k:03d}.tif", "cam1_{k:03d}.tif")])
def test_a_folder_with_both_views_gets_the_left_and_right_patterns(tmp_path, left_name, right_name):
    """``specula stereo FOLDER`` with the left and right images in one folder said "got 1"; it now names the
    --left/--right glob patterns that split the folder, and those patterns select exactly each view."""
    import re

    from dic.io import write_image
    from dic.sources import open_inputs

    folder = tmp_path / "both"
    folder.mkdir()
    image = (np.arange(64 * 80).reshape(64, 80) % 251).astype(np.uint8)
    lefts = [write_image(folder / left_name.format(k=k), image) for k in range(3)]
    rights = [write_image(folder / right_name.format(k=k), image) for k in range(3)]
    r = CliRunner().invoke(main, ["stereo", "--rig", str(tmp_path / "rig.json"), str(folder), "-o",
                                  str(tmp_path / "out.h5")], terminal_width=400)
    assert r.exit_code == 2 and "got 1" in r.output, r.output
    found = re.search(r"--left '([^']+)' --right '([^']+)'", r.output.replace("\n", " "))
    assert found, r.output
    assert "(3 image(s)" in r.output
    for pattern, files in zip(found.groups(), (lefts, rights)):
        assert open_inputs([pattern]).files == [str(f) for f in files]
    # a folder of one view only: the general advice
    (tmp_path / "one").mkdir()
    write_image(tmp_path / "one" / "a.png", image)
    r = CliRunner().invoke(main, ["stereo", "--rig", str(tmp_path / "rig.json"), str(tmp_path / "one"), "-o",
                                  str(tmp_path / "out.h5")])
    assert r.exit_code == 2 and "give the left and right sequences as two inputs, or with --left and --right" in r.output


@pytest.mark.parametrize("subset", [15, 21, 31])
def test_one_default_step_rule_subset_over_two(images, tmp_path, fake, subset):  # noqa: F811 - fixtures
    """The CLI's default step was 5 (track) and 10 (stereo), the library's subset // 2 (2-D) and 10 (stereo):
    every one is now subset // 2."""
    from dic.sequence.options import StereoOptions, TrackOptions

    assert TrackOptions(subset=subset).step == StereoOptions(subset=subset).step == subset // 2
    out = tmp_path / "res.h5"
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--subset", str(subset)])
    assert r.exit_code == 0, r.output
    res = read_results(out)
    assert res.settings["step"] == subset // 2
    xs = np.unique(res.frames[1].points[:, 0])
    assert np.all(np.diff(xs) == subset // 2)  # the grid the run tracked


def test_stereo_correlation_default_step_is_subset_over_two():
    """dic._stereo.StereoCorrelation's own default (without the run record) follows the same rule."""
    import inspect

    from dic._stereo import StereoCorrelation, stereo

    for fn in (StereoCorrelation.__init__, stereo):
        assert inspect.signature(fn).parameters["step"].default is None
    from dic.commands.stereo import stereo as stereo_command

    step_option = next(p for p in stereo_command.params if p.name == "step")
    assert step_option.default is None and "subset // 2" in step_option.help


def test_ctrl_c_in_stereo_says_how_many_states_are_saved(tmp_path, monkeypatch):
    """Ctrl-C once state 1 is written (raised from the run's callback): 2 states (0 and 1) are in the file."""
    import dic.sequence
    from dic.store import read_stereo

    paths = _stereo_scene(tmp_path)
    real = dic.sequence.stereo_sequence

    def interrupted(*args, callback=None, **kwargs):
        def stop(index, field, strain):
            callback(index, field, strain)
            if index == 1:
                raise KeyboardInterrupt

        return real(*args, callback=stop, **kwargs)

    monkeypatch.setattr(dic.sequence, "stereo_sequence", interrupted)
    out = tmp_path / "run.h5"
    args = ["stereo", "--rig", str(tmp_path / "rig.json"), *paths * 3, "--step", "20", "-q", "-o", str(out)]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 130, r.output
    assert f"Interrupted: 2 states saved in {out}; run the same command again to resume" in r.output
    assert read_stereo(out).indices == [0, 1]
