"""The ``specula`` command line.

Each subcommand lives in its own module under ``dic/commands/`` and is imported only when it is
invoked, so ``specula --help`` stays fast and one broken command cannot take the others down.
"""
from __future__ import annotations

import importlib
import warnings

import click

from kernels.conventions import DISTRIBUTION_NAME

# name -> "module:attribute" of a click command or group
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "track": ("dic.commands.track:track", "2D DIC: track a reference image into one or more current images"),
    "lab": ("dic.commands.lab:lab", "Virtual lab: render scenes of cameras, mirrors, monitors and speckle"),
    "target": ("dic.commands.target:target", "Calibration targets: write phase-fringe / dot / checkerboard images"),
    "calibrate": ("dic.commands.calibrate:calibrate", "Calibrate intrinsics, mirror extrinsics or a stereo rig"),
    "stereo": ("dic.commands.stereo:stereo", "Stereo-DIC: 3D shape, displacement and strain"),
    "strain": ("dic.commands.postprocess:strain", "Recompute the strain of a 2D or stereo result file with another window or type"),
    "extensometer": ("dic.commands.postprocess:extensometer", "Virtual extensometer: gauge length and strain per frame"),
    "history": ("dic.commands.postprocess:history", "A quantity at one point over the frames"),
    "profile": ("dic.commands.postprocess:profile", "A quantity along a line, per frame"),
    "export": ("dic.commands.export:export", "Export a result file as CSV, MATLAB, netCDF, VTK (ParaView) or PLY point clouds"),
    "animate": ("dic.commands.animate:animate", "A movie (MP4, GIF) of one quantity over the frames of a result file"),
    "speckle": ("dic.commands.speckle:speckle", "Speckle quality (MIG, SSSIG) and a subset size for a target uncertainty"),
    "report": ("dic.commands.report:report", "One self-contained HTML report of a result file: settings, quality, maps"),
    "repair": ("dic.commands.repair:repair", "Drop the damaged frames of a result file so that a rerun recomputes them"),
    "crack": ("dic.commands.crack:crack", "Opening and sliding of declared cracks along their polylines (2D results)"),
}


#: exceptions a user can cause (bad values, missing or unwritable files, a full disk, a locked file):
#: the CLI reports them as ``Error: <message>`` with exit status 1 and no traceback. Any other
#: exception type is a bug and keeps its traceback.
USER_ERRORS = (ValueError, OSError)


def user_message(exc: BaseException) -> str:
    """One line for a user error: the library's message, or ``path: reason`` for an OSError."""
    if isinstance(exc, OSError) and exc.strerror:
        names = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        return f"{' -> '.join(names)}: {exc.strerror}" if names else exc.strerror
    text = str(exc).strip()
    return text or type(exc).__name__


class _NonEmpty(click.ParamType):
    """A parameter type that refuses an empty (or blank) string, then converts with the type it wraps.

    Wrapped around every option and argument that takes a path or free text (a shape, a point, a frame
    list, a device, ...): ``--roi-polygon ""`` would otherwise be ignored and ``--vtk ""`` write into the
    current folder. Nothing in Specula takes an empty string on purpose.
    """

    def __init__(self, inner: click.ParamType):
        self.inner = inner
        self.name = inner.name
        self.envvar_list_splitter = inner.envvar_list_splitter
        self.is_composite = inner.is_composite
        self.arity = inner.arity

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            hint = ", or leave the option out" if isinstance(param, click.Option) and not param.required else ""
            self.fail(f"must not be empty: give a value{hint}", param, ctx)
        return self.inner.convert(value, param, ctx)

    def get_metavar(self, *args, **kwargs):
        return self.inner.get_metavar(*args, **kwargs)

    def get_missing_message(self, *args, **kwargs):
        return self.inner.get_missing_message(*args, **kwargs)

    def to_info_dict(self):
        return self.inner.to_info_dict()

    def shell_complete(self, ctx, param, incomplete):
        return self.inner.shell_complete(ctx, param, incomplete)

    def __repr__(self) -> str:
        return repr(self.inner)


def refuse_empty_strings(command: click.Command) -> click.Command:
    """Make every path or text parameter of ``command`` (and of its subcommands) refuse ``""`` (see
    :class:`_NonEmpty`); choices and numbers refuse it already. Returns the command."""
    if getattr(command, "_specula_nonempty", False):
        return command
    for param in command.params:
        if isinstance(param.type, (click.Path, click.types.StringParamType)) and not isinstance(param.type, _NonEmpty):
            param.type = _NonEmpty(param.type)
    for sub in getattr(command, "commands", {}).values():
        refuse_empty_strings(sub)
    command._specula_nonempty = True
    return command


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        return sorted(SUBCOMMANDS)

    def get_command(self, ctx, name):
        if name not in SUBCOMMANDS:
            return None
        target, short_help = SUBCOMMANDS[name]
        module_name, attr = target.split(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise

            @click.command(name=name, help=short_help + " (not available in this version)")
            def unavailable():
                raise click.ClickException(f"'specula {name}' is not available in this version")

            return unavailable
        return refuse_empty_strings(getattr(module, attr))

    def invoke(self, ctx):
        """Run the subcommand; an error the user can cause becomes one clear message (exit status 1). A closed
        stdout (``specula history ... | head -1``) ends the command quietly (exit status 1, as click does)."""
        try:
            return super().invoke(ctx)
        except BrokenPipeError:  # the reader of stdout went away (``| head``): click exits quietly, no "Error: Broken pipe"
            raise
        except USER_ERRORS as exc:
            raise click.ClickException(user_message(exc)) from None

    def format_commands(self, ctx, formatter):
        rows = [(name, SUBCOMMANDS[name][1]) for name in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name=DISTRIBUTION_NAME, prog_name="specula")
def main():
    """Specula: stereo digital image correlation on Warp kernels."""
    warnings.showwarning = _show_warning


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Library warnings (e.g. "only 0 of 2304 points are valid ... try --search") as plain messages."""
    click.echo(f"Warning: {message}", err=True)


if __name__ == "__main__":  # pragma: no cover
    main()
