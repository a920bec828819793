"""Referee 6: an independent close-loop referee (own generator, own oracle)."""
