"""The calibration daemon's logic, without I/O: `Calibrator` (the state machine) and the
listeners it tells its states and results to; `calibd.live` wires it to a sample source."""

from .calibrator import Calibrator
from .events import Callbacks, Listener, State, StateLog
from .solver import stale_result
from .trimmer import Trimmer

__all__ = ["Calibrator", "Callbacks", "Listener", "State", "StateLog", "Trimmer", "stale_result"]
