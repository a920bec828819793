"""An independent held-out generator and referee for close-the-loop (issue 12).

Written from the physics and the issue's rules only, without the product's effect library or the
in-repo corpus: ``cases`` draws units, thermal programs, noise and hidden effects with their truth;
``score`` runs the product's close-the-loop on them and scores each channel.
"""
