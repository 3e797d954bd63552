"""Moved to :mod:`geonet_infer.eval.datasets` (issue 42: evaluation is out of the runtime's import path).

This alias goes in the next release; each use of an old name warns (DeprecationWarning).
"""

from geonet_infer._moved import forward

__getattr__ = forward(__name__, "geonet_infer.eval.datasets", renamed={"TASKS": "EVAL_TASKS"})
