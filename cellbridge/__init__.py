"""cellbridge: software for a large-area soft robot skin built on the cell-bridge system.

The layers live in sub-packages: :mod:`cellbridge.protocol` (wire protocol),
:mod:`cellbridge.tactile` (element physics and contact estimation),
:mod:`cellbridge.emulator` (bridge-chip emulator) and :mod:`cellbridge.daemon`
(the host service).
"""

from cellbridge._version import __version__

__all__ = ["__version__"]
