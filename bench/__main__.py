"""``python -m bench``: the ``bench`` command line."""
from bench.cli import app

if __name__ == "__main__":
    app(prog_name="bench")
