"""Assistance signals behind one interface: the paper's denoising metric and the baselines it is
compared against (output variance, Diff-DAgger, ThriftyDAgger, STAC, HULA-offline), our ``spread``,
``stall``, ``choice`` and the fleet's ``choice-stall``, plus the ``full-teleop`` and ``random`` references.

- ``base``: ``AssistanceSignal``, ``SignalInput``, ``Scores``, ``TriggerState``, ``CalibrationData``
- ``sampling``, ``spread``, ``stall``, ``choice``, ``choice_stall``: signals computed from the diffusion
  policy alone
- ``critics`` / ``aux``: signals with learned auxiliary networks and their training loops
- ``registry``: ``SIGNALS``, ``make_signal``, ``save_signal`` / ``load_signal``
- (``policy.signal_data``, beside this package: the policy's demonstration split and its own rollouts as
  calibration data)
"""

from policy.signals.base import AssistanceSignal, CalibrationData, Scores, SignalError, SignalInput, TriggerState
from policy.signals.registry import SIGNALS, load_signal, make_signal, save_signal

__all__ = [
    "SIGNALS",
    "AssistanceSignal",
    "CalibrationData",
    "Scores",
    "SignalError",
    "SignalInput",
    "TriggerState",
    "load_signal",
    "make_signal",
    "save_signal",
]
