"""The bundled sample sequence: frames from our own synthetic scene generator (training.synth).

Made by ``scripts/build_bundled_model.sh`` from a held-out synthetic sequence (never trained on).
"""

from pathlib import Path

SAMPLE_DIR = Path(__file__).resolve().parent / "synth_seq"
SAMPLE_FRAMES = SAMPLE_DIR / "image"
SAMPLE_CALIB = SAMPLE_DIR / "calib.txt"
