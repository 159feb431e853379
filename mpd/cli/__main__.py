"""``python -m mpd.cli``: the ``mpd`` command."""

from mpd.cli import main

main()
