"""Specula's user-facing DIC engine: grids, tracking, strain, stereo, results, CLI and the virtual lab."""
__all__: list[str] = []
