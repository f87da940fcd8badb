"""Which shard stream a process reads, from the launcher's environment.

A pipeline serves the ranks of *its host*: ``--world-size W`` streams
``superflow/<run>/rank/0..W-1`` on every host (``--host-rank h --host-count H`` deal the
dataset between the hosts). So a rank reads the stream of its rank on its host:

1. ``rank=`` / ``world_size=`` given to ``Stream``: used as they are (``world_size=1``
   reads the broadcast stream).
2. torchrun / ``torch.distributed.run`` (``WORLD_SIZE`` above 1): ``LOCAL_RANK`` of
   ``LOCAL_WORLD_SIZE`` when set (the rank on this node), else ``RANK`` of ``WORLD_SIZE``
   (one node).
3. Slurm without torchrun (``SLURM_NTASKS`` above 1): ``SLURM_LOCALID`` of
   ``SLURM_NTASKS_PER_NODE`` on several nodes, ``SLURM_PROCID`` of ``SLURM_NTASKS`` on
   one.
4. Otherwise the broadcast stream.
"""

from __future__ import annotations

import os
from typing import NamedTuple


class Shard(NamedTuple):
    """The stream of a process: ``rank`` of ``world_size`` on this host (None: the
    broadcast stream), and the process's place in the whole job (``job_rank`` of
    ``job_size``, equal to the host's on one host); ``source`` says where it came from."""

    rank: int | None
    world_size: int | None
    job_rank: int
    job_size: int
    source: str


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"environment variable {name}={value!r} is not an integer") from None


def _need(name: str, why: str) -> int:
    value = _env_int(name)
    if value is None:
        raise ValueError(f"{why} without {name} (set it, or pass rank= and world_size=)")
    return value


def _tasks_per_node() -> int | None:
    """SLURM_NTASKS_PER_NODE, or this node's entry of SLURM_TASKS_PER_NODE ("4(x2),3")
    when every node has the same count."""
    value = _env_int("SLURM_NTASKS_PER_NODE")
    if value is not None:
        return value
    spec = os.environ.get("SLURM_TASKS_PER_NODE", "")
    counts = {part.split("(")[0] for part in spec.split(",") if part}
    if len(counts) == 1:
        try:
            return int(counts.pop())
        except ValueError:
            return None
    return None


def resolve(rank: int | None, world_size: int | None) -> Shard:
    """The shard of this process (see the module docs)."""
    if rank is not None or world_size is not None:
        if rank is None and world_size is not None and world_size > 1:
            rank = _env_int("LOCAL_RANK") if _env_int("LOCAL_WORLD_SIZE") == world_size else None
            rank = _env_int("RANK") if rank is None else rank
            if rank is None:
                raise ValueError(f"world size {world_size} without a rank (set RANK or pass rank=)")
        if rank is None:
            return Shard(None, None, 0, 1, "arguments")
        return _checked(Shard(rank, world_size, rank or 0, world_size or 1, "arguments"))
    world = _env_int("WORLD_SIZE")
    if world is not None and world > 1:
        job_rank = _need("RANK", f"WORLD_SIZE={world}")
        local_world = _env_int("LOCAL_WORLD_SIZE")
        if local_world is not None and local_world < world:
            local = _need("LOCAL_RANK", f"LOCAL_WORLD_SIZE={local_world}")
            return _checked(Shard(local, local_world, job_rank, world,
                                  "LOCAL_RANK/LOCAL_WORLD_SIZE"))
        return _checked(Shard(job_rank, world, job_rank, world, "RANK/WORLD_SIZE"))
    tasks = _env_int("SLURM_NTASKS")
    if world is None and tasks is not None and tasks > 1:
        job_rank = _need("SLURM_PROCID", f"SLURM_NTASKS={tasks}")
        nodes = _env_int("SLURM_NNODES") or _env_int("SLURM_JOB_NUM_NODES") or 1
        if nodes > 1:
            per_node = _tasks_per_node()
            if per_node is None:
                raise ValueError(f"SLURM_NTASKS={tasks} on {nodes} nodes: set "
                                 "SLURM_NTASKS_PER_NODE (--ntasks-per-node), or pass rank= and "
                                 "world_size= (the rank on this node's pipeline)")
            local = _need("SLURM_LOCALID", f"SLURM_NNODES={nodes}")
            return _checked(Shard(local, per_node, job_rank, tasks,
                                  "SLURM_LOCALID/SLURM_NTASKS_PER_NODE"))
        return _checked(Shard(job_rank, tasks, job_rank, tasks, "SLURM_PROCID/SLURM_NTASKS"))
    return Shard(None, None, 0, 1, "broadcast")


def _checked(shard: Shard) -> Shard:
    if shard.rank is not None and (shard.rank < 0 or (shard.world_size is not None
                                                      and shard.rank >= shard.world_size)):
        raise ValueError(f"rank {shard.rank} is outside world size {shard.world_size} "
                         f"(from {shard.source})")
    return shard
