"""rotlearn: deep rotation learning with uncertainty.

Quaternions are scalar LAST everywhere: q = (x, y, z, w), Hamilton product, active rotations.
"""

__version__ = "0.1.0"
