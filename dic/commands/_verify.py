"""``--verify-spread`` of ``specula track`` and ``specula stereo``: the robust standard deviations below a frame's
median composed ZNCC that can lower ``--verify-zncc`` (:func:`kernels.verify.composed_threshold`)."""
from __future__ import annotations

import click


def parse_verify_spread(text):
    """None (not given: the library's default), ``"off"``, or a finite number >= 0 (float); a BadParameter else."""
    if text is None:
        return None
    from kernels.verify import check_verify_spread

    if str(text).strip().lower() == "off":
        return "off"
    try:
        return check_verify_spread(float(text))
    except ValueError:
        raise click.BadParameter(f"expected a number >= 0 (robust standard deviations) or 'off', got {text!r}",
                                 param_hint="--verify-spread") from None
