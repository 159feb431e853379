"""The priors shipped with mpd for every task but the Panda ones (mpd-priors-panda), as a distribution of their own
(the mpd wheel stays small): the folder ``ROOT`` holds
``models/<task>/<kind>-<parametrization>-<identity>.pt`` with lock files and ``<task>/dataset-*`` digests, laid out
as ``mpd/priors/`` of the repository. mpd finds it through the ``mpd.priors`` entry point."""

from pathlib import Path

ROOT = Path(__file__).resolve().parent
