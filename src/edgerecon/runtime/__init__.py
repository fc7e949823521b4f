"""The online system: front-end and back-end roles, the embedded and Ray engines, the session.

See :mod:`edgerecon.runtime.frontend`, :mod:`edgerecon.runtime.backend`,
:mod:`edgerecon.runtime.engine`, :mod:`edgerecon.runtime.ray_engine` and
:mod:`edgerecon.runtime.session`; :func:`run_online` assembles them.
"""

from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.runtime.online import make_controller, run_online
from edgerecon.runtime.session import FrameRange, RunSummary, SessionOptions

__all__ = [
    "FrameRange",
    "RunSummary",
    "RuntimeConfig",
    "SessionOptions",
    "TaskMetrics",
    "make_controller",
    "run_online",
]
