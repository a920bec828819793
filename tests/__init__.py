from pathlib import Path

#: the seed papers' reference tables, in ``../shared/reference`` beside the checkout
REFERENCE_DIR = Path(__file__).resolve().parents[2] / "shared" / "reference"
