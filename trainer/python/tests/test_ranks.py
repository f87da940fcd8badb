"""Which stream a process reads under torchrun, Slurm or explicit arguments."""

from __future__ import annotations

import pytest

from superflow import ranks

LAUNCHER_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "SLURM_NTASKS",
                      "SLURM_PROCID", "SLURM_LOCALID", "SLURM_NNODES", "SLURM_JOB_NUM_NODES",
                      "SLURM_NTASKS_PER_NODE", "SLURM_TASKS_PER_NODE")


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in LAUNCHER_VARIABLES:
        monkeypatch.delenv(name, raising=False)


def test_a_lone_process_reads_the_broadcast_stream() -> None:
    assert ranks.resolve(None, None) == ranks.Shard(None, None, 0, 1, "broadcast")


def test_torchrun_on_one_node_uses_the_global_rank(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RANK", "3")
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "3")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    assert ranks.resolve(None, None) == ranks.Shard(3, 4, 3, 4, "RANK/WORLD_SIZE")


def test_torchrun_on_two_nodes_uses_the_rank_on_the_node(monkeypatch: pytest.MonkeyPatch) -> None:
    # Node 1 of `torchrun --nnodes 2 --nproc-per-node 4`: global ranks 4..7.
    monkeypatch.setenv("RANK", "6")
    monkeypatch.setenv("WORLD_SIZE", "8")
    monkeypatch.setenv("LOCAL_RANK", "2")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    shard = ranks.resolve(None, None)
    assert (shard.rank, shard.world_size, shard.job_rank, shard.job_size) == (2, 4, 6, 8)
    assert shard.source == "LOCAL_RANK/LOCAL_WORLD_SIZE"


def test_slurm_without_torchrun(monkeypatch: pytest.MonkeyPatch) -> None:
    for name, value in {"SLURM_NTASKS": "8", "SLURM_PROCID": "5", "SLURM_LOCALID": "1",
                        "SLURM_NNODES": "2", "SLURM_TASKS_PER_NODE": "4(x2)"}.items():
        monkeypatch.setenv(name, value)
    shard = ranks.resolve(None, None)
    assert (shard.rank, shard.world_size, shard.job_rank, shard.job_size) == (1, 4, 5, 8)
    monkeypatch.setenv("SLURM_NNODES", "1")
    monkeypatch.setenv("SLURM_NTASKS", "4")
    monkeypatch.setenv("SLURM_PROCID", "2")
    assert ranks.resolve(None, None).rank == 2


def test_torchrun_wins_over_slurm(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SLURM_NTASKS", "8")
    monkeypatch.setenv("SLURM_PROCID", "5")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert ranks.resolve(None, None).rank == 1


def test_arguments_win_and_are_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RANK", "6")
    monkeypatch.setenv("WORLD_SIZE", "8")
    assert ranks.resolve(1, 2).rank == 1
    assert ranks.resolve(None, 1).rank is None  # world_size=1: the broadcast stream
    assert ranks.resolve(0, 1).rank == 0
    with pytest.raises(ValueError, match="outside world size"):
        ranks.resolve(2, 2)


def test_missing_or_bad_variables_are_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WORLD_SIZE", "4")
    with pytest.raises(ValueError, match="RANK"):
        ranks.resolve(None, None)
    monkeypatch.setenv("RANK", "two")
    with pytest.raises(ValueError, match="RANK='two'"):
        ranks.resolve(None, None)
    monkeypatch.setenv("RANK", "2")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="LOCAL_RANK"):
        ranks.resolve(None, None)
