"""The referee corpus for close-the-loop: generated cases with known truth (``cases``), the physics
behind them (``physics``, ``effects``, ``generator``), the referee (``referee``) and the scoring script
(``python -m tests.corpus.score``)."""
