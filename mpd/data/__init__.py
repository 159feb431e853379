"""Datasets of collision-free paths: contexts, OMPL planning, definitions, storage and versioning.

Modules (nothing is imported here: OMPL, PyBullet and torch load only where they are used):

* ``definition``: ``datasets/NAME.toml`` -> :class:`~mpd.data.definition.ResolvedDefinition` (identity, paths)
* ``generate``: :func:`~mpd.data.generate.generate` (parallel, resumable) and the lock file
* ``dataset``: :func:`~mpd.data.dataset.load_dataset` -> :class:`~mpd.data.dataset.Dataset`
* ``contexts``: start/goal sampling, :func:`~mpd.data.contexts.evaluation_contexts`
* ``planning``: RRTConnect + simplifyMax + resampling, :func:`~mpd.data.planning.plan_path`
* ``checkers``: the sphere model in numpy and PyBullet meshes, both with a clearance
* ``storage``: byte-reproducible chunk files; ``measure``: sphere model vs meshes, checker speeds
"""
