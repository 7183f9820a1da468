"""Image sequences, 2-D and stereo, on one pipelined engine (docs/dic2d.md "Sequences", docs/stereo.md).

- :func:`track_sequence` (:mod:`dic.sequence.track2d`): 2-D DIC of a sequence against a reference
  image, with the reference strategies of :mod:`dic.sequence.reference` ("fixed", "incremental",
  "every:N", "auto"; results always Lagrangian), streaming VTK files and figures, resume.
- :func:`stereo_sequence` (:mod:`dic.sequence.stereo`): stereo DIC of a sequence of image pairs, with
  the same reference strategies for its temporal tracks (the left -> right match done once; results
  Lagrangian, ``reference_index`` per state), streaming VTK files and figures, resume.
- :mod:`dic.sequence.engine`: the one sequence loop both run on (resume checks, reference policy, the
  ``auto`` retry, the Dask window), :class:`SequenceSummary` (what either returns).
- :mod:`dic.sequence.pipeline`: the reader thread ahead, the writer thread behind, ``malloc_trim``.
- :mod:`dic.sequence.options`: the run record (:class:`TrackOptions`, :class:`StereoOptions`), every
  option that affects the results, stored in the file with its defaults and compared on resume.
"""
from __future__ import annotations

from .engine import SequenceSummary
from .options import OptionError, StereoOptions, TrackOptions
from .reference import ReferencePolicy, parse_reference
from .stereo import FORMAT_NAME, SCHEMA_VERSION, StereoResults, read_field, read_stereo, stereo_sequence
from .track2d import track_sequence

__all__ = ["track_sequence", "SequenceSummary", "stereo_sequence", "read_stereo", "read_field", "StereoResults",
           "FORMAT_NAME", "SCHEMA_VERSION", "ReferencePolicy", "parse_reference", "TrackOptions", "StereoOptions",
           "OptionError"]
