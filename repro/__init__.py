"""Research code of Specula: the paper reproduction and the studies behind the documented figures.

Not installed with the library (pyproject installs ``kernels``, ``calibration`` and ``dic`` only);
run from the repository root, e.g. ``python -m repro.demo --out demo_output`` or
``python -m repro.paper``. Index and how to run each study: repro/README.md.

Modules
-------
experiments        the paper's Section 3 experiments in the virtual lab (calibration → measurement → metrics)
paper              the full reproduction: ``docs/paper_reproduction.md`` and ``repro/results/paper.json``
demo               the end-to-end demo of ``make demo`` (2-D DIC, then the stereo chain on the paper rig)
calibration_lab    the calibration of the paper rig from rendered images, against the lab's truth
intrinsics_design  Monte Carlo: how many direct views a mirror-calibrated rig needs (and the σ check)
mirror_setup       the exact geometry of the paper's mirror calibration (``paper_mirror_setup``)
mirror_accuracy    Monte Carlo accuracy of mirror vs checkerboard rig calibration on that geometry
targets            accuracy of the calibration-target detectors on synthetic views

The paper's numbers (baseline, working distance, monitor, mirrors) are defined once, in
:mod:`dic.lab.paper`; every module here imports them.
"""
