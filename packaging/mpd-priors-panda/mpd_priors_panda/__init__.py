"""The priors of the Franka Panda tasks shipped with mpd, as a distribution of their own (mpd-priors holds the other
tasks'; one wheel of all of them would pass PyPI's 100 MB limit): the folder ``ROOT`` holds
``models/<task>/<kind>-<parametrization>-<identity>.pt`` with lock files and ``<task>/dataset-*`` digests, laid out
as ``mpd/priors/`` of the repository. mpd finds it through the ``mpd.priors`` entry point."""

from pathlib import Path

ROOT = Path(__file__).resolve().parent
