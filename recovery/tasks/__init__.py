"""The tasks ``recovery train`` trains, by the name a config's ``task`` gives: HMR-BLSM
(``hmr_blsm``, :mod:`.hmr_task`), the image-to-mesh network (``mesh``, :mod:`.mesh_task`) and the
mesh autoencoder (``autoencoder``, :mod:`.ae_task`). Each registers a
:class:`recovery.tasks.base.TaskSpec`; a new network adds its module and one entry here.
"""

from __future__ import annotations

from recovery.tasks import ae_task, hmr_task, mesh_task
from recovery.tasks.base import TaskSpec

TASKS: dict[str, TaskSpec] = {spec.name: spec for spec in (hmr_task.SPEC, mesh_task.SPEC, ae_task.SPEC)}


def get_task(name: str) -> TaskSpec:
    """The :class:`TaskSpec` of ``name``; a ValueError lists the known tasks."""
    try:
        return TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; known: {', '.join(TASKS)}") from None
