#!/usr/bin/env bash
# One rank of a data-parallel job (`superflow-trainer --ddp`): picks the GPU of the
# rank's local rank on its host, then runs the trainer with the arguments given.
#
#   srun --mpi=pmix ... deploy/superflow-ddp-rank.sh --ddp --run exp1 ...   (Slurm)
#   mpirun -np 8 ... superflow-ddp-rank --ddp --run exp1 ...               (the image)
#
# Local rank: OMPI_COMM_WORLD_LOCAL_RANK under Open MPI's mpirun, SLURM_LOCALID under
# srun. GPU = local rank, for both backends: `--device-index` (cuda) and
# CUBECL_WGPU_DEFAULT_DEVICE=DiscreteGpu(i) (wgpu, which ignores --device-index and
# CUDA_VISIBLE_DEVICES). Every rank must then see all GPUs of its host (Slurm: no
# --gpu-bind; Kubernetes: all of the pod's GPUs in one container). Where each rank sees
# only its own GPU (srun --gpus-per-task=1 --gpu-bind=single:1), set
# SUPERFLOW_DEVICE_INDEX=0. Do not pass --device-index yourself.
# The trainer is $SUPERFLOW_BIN/superflow-trainer (default /usr/local/bin, the image's).
set -euo pipefail

local_rank="${OMPI_COMM_WORLD_LOCAL_RANK:-${SLURM_LOCALID:-0}}"
gpu="${SUPERFLOW_DEVICE_INDEX:-$local_rank}"
export CUBECL_WGPU_DEFAULT_DEVICE="${CUBECL_WGPU_DEFAULT_DEVICE:-DiscreteGpu($gpu)}"
bin="${SUPERFLOW_BIN:-/usr/local/bin}"
exec "$bin/superflow-trainer" --device-index "$gpu" "$@"
