"""Referee 7: an outside lab's physics-based test referee for ``bench close-loop`` (see score.py)."""
