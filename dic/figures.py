"""Moved to :mod:`dic.plots.fields`; this name stays until ``dic/demo.py`` (moving to ``repro/``) imports from there."""
from .plots.fields import field_figure, write_field_figure

__all__ = ["field_figure", "write_field_figure"]
