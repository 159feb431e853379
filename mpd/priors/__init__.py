"""Shipped priors (data only): trained checkpoints with their lock files, one folder per task. See
:mod:`mpd.models.shipped` and README.md here."""
