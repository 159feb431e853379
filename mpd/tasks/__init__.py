"""Task files (the paper's six tasks and their extra-object variants) and their loader."""

from mpd.tasks.spec import CostWeights, TaskSpec, TrainingSpec
from mpd.tasks.task import Task, list_tasks, load_task, resolve_task_path, task_files

__all__ = [
    "CostWeights",
    "Task",
    "TaskSpec",
    "TrainingSpec",
    "list_tasks",
    "load_task",
    "resolve_task_path",
    "task_files",
]
