"""Outputs: static figures (``mpd.viz.scene``), Rerun recordings and reports.

Nothing is imported here on purpose: matplotlib, seaborn and rerun are heavy, and each caller pays only for
what it uses (``from mpd.viz.scene import task_figure``).
"""
