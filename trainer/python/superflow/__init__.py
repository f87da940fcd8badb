"""superflow: SuperFlow training batches from a running ``superflow-pipeline``, zero-copy.

    import superflow
    stream = superflow.Stream(run="exp1")          # RANK / WORLD_SIZE select a shard
    for epoch in range(E):
        for batch in stream.epoch():               # this rank's batches of one epoch
            points = batch["points"]               # numpy view into shared memory
            tensors = batch.torch()                # torch.Tensor views (torch optional)
    for batch in stream: ...                       # every batch until the pipeline's last epoch

The sections and their meaning: schemas/BATCH_FORMAT.md in the superflow repository
(``superflow.sections`` has the names and dtypes).
"""

from typing import Any

from .batch import Batch, SectionArray
from .errors import (
    BatchReleased,
    FormatVersionMismatch,
    MalformedBatch,
    PipelineTimeout,
    PlanMismatch,
    ResumeRefused,
    RunComplete,
    ScheduleUnavailable,
    StreamNotPicklable,
    SuperflowError,
    TooManyBatchesHeld,
    WorkersUnsupported,
)
from .format import deprecated_name, read_batch
from .sections import BATCH_SECTIONS, LEVEL_SECTIONS, section_dtype
from .stream import Epoch, Stream
from .wire import Schedule

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    # torch is imported only when TorchIterable is asked for: `import superflow` stays
    # quick (importing torch maps ~1.5 GB of libraries) and works without torch.
    if name == "TorchIterable":
        from .torch_data import TorchIterable

        return TorchIterable
    if name == "torch":  # superflow.torch.spconv_tensor, without `import superflow.torch`
        import importlib

        return importlib.import_module(".torch", __name__)
    # BatchFormatError, FormatVersionError: the old names of MalformedBatch and
    # FormatVersionMismatch, with a DeprecationWarning.
    return deprecated_name(__name__, name)

__all__ = [
    "BATCH_SECTIONS",
    "LEVEL_SECTIONS",
    "Batch",
    "BatchReleased",
    "Epoch",
    "FormatVersionMismatch",
    "MalformedBatch",
    "PipelineTimeout",
    "PlanMismatch",
    "ResumeRefused",
    "RunComplete",
    "Schedule",
    "ScheduleUnavailable",
    "SectionArray",
    "Stream",
    "StreamNotPicklable",
    "SuperflowError",
    "TooManyBatchesHeld",
    "TorchIterable",
    "WorkersUnsupported",
    "read_batch",
    "section_dtype",
]
