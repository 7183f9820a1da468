"""Camera and rig models, phase targets, feature extraction and calibration (float64, NumPy/SciPy/OpenCV)."""
__all__: list[str] = []
