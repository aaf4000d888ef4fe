"""A Python client for rigd, the BTF rig control daemon (HTTP API ``/api/v1``).

>>> from rigd_client import Client
>>> rigd = Client("http://127.0.0.1:8080", data_dir="rigd-data")
>>> run = rigd.start_run("felt-3", "h1", frame_size=(64, 48))
>>> rigd.wait(run)["state"]
'completed'
"""

from ._client import (
    DEFAULT_URL,
    Client,
    direction,
    inline_plan,
    is_fault_pause,
    resolve_token,
    run_request,
)
from ._errors import RigdError, RigdTimeout
from ._types import (
    FINAL_STATES,
    JOB_FINAL_STATES,
    CommandAck,
    Enqueued,
    Event,
    Health,
    ProcessJob,
    QueueItem,
    Render,
    RunPage,
    RunView,
)

__all__ = [
    "Client",
    "CommandAck",
    "DEFAULT_URL",
    "Enqueued",
    "Event",
    "FINAL_STATES",
    "Health",
    "JOB_FINAL_STATES",
    "ProcessJob",
    "QueueItem",
    "Render",
    "RigdError",
    "RigdTimeout",
    "RunPage",
    "RunView",
    "direction",
    "inline_plan",
    "is_fault_pause",
    "resolve_token",
    "run_request",
]
__version__ = "0.1.0"
