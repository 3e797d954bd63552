"""Moved to :mod:`geonet_infer.core.results` (issue 42: the core is what ``load()`` runs).

This alias goes in the next release; each use of an old name warns (DeprecationWarning).
"""

from geonet_infer._moved import forward

__getattr__ = forward(__name__, "geonet_infer.core.results")
