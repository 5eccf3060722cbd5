"""The options of the loss's parts (and the paper's preset, ``PAPER_OPTIONS``).

They are defined once, in :mod:`wcsac_rl.options` (which imports no torch, so that the
config can be composed from them without loading it); this module names them where the
loss lives.
"""

from wcsac_rl.options import PAPER_OPTIONS, IQNOptions, PIDGains, SafetyOptions

__all__ = ["PAPER_OPTIONS", "IQNOptions", "PIDGains", "SafetyOptions"]
