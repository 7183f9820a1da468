"""The ``--robust`` / ``--robust-mode`` options of ``specula track`` and ``specula stereo``.

``--robust`` keeps its meaning (every accepted point refined by Tukey-weighted IC-GN); ``--robust-mode``
chooses among ``off`` (plain IC-GN; the default of ``specula stereo``), ``on`` (the same as ``--robust``) and
``adaptive`` (robust IC-GN only for the subsets whose plain residuals show a compact blob of outliers,
:mod:`kernels.icgn_robust`; the default of ``specula track``: docs/dic2d.md, "Robust correlation").
"""
from __future__ import annotations

import click

__all__ = ["ROBUST_MODES", "robust_mode_option", "robust_value"]

#: the ``--robust-mode`` choices -> the library's ``robust`` value
ROBUST_MODES = {"off": False, "on": True, "adaptive": "adaptive"}


def robust_mode_option(what: str, default: str = "off"):
    """The ``--robust-mode`` click option; ``what`` names what is correlated, ``default`` the mode without it."""
    return click.option(
        "--robust-mode", default=None, type=click.Choice(sorted(ROBUST_MODES)),
        help=f"Outlier-robust IC-GN of {what} (default: {default}): 'adaptive' refines with Tukey-weighted IC-GN only "
             "the subsets whose plain residuals show a compact blob of outliers (a changed speckle, a glint) and keeps the "
             "plain result of every other subset exactly; 'on' (= --robust) refines every point; 'off': plain IC-GN.")


def robust_value(flag: bool, mode: str | None, default: str = "off"):
    """The library's ``robust`` from ``--robust`` (``flag``) and ``--robust-mode`` (``mode``, None: not given:
    ``default``, the command's default mode)."""
    if mode is None:
        return True if flag else ROBUST_MODES[default]
    if mode not in ROBUST_MODES:
        raise click.BadParameter(f"must be one of {', '.join(sorted(ROBUST_MODES))}, got {mode!r}",
                                 param_hint="--robust-mode")
    if flag and mode != "on":
        raise click.BadParameter(f"--robust means --robust-mode on; it contradicts --robust-mode {mode}",
                                 param_hint="--robust-mode")
    return ROBUST_MODES[mode]
