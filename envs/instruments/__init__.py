"""Instruments: what acts on the tissue of a :class:`heml_gym.World`, one object per instrument
standing for it in every world of the batch, each owning its slice of the action, its part
of the observation and its ``info`` entries: :class:`Grasper` (jaws), :class:`Paddle` (a
blunt retractor that pushes and lifts) and :class:`Hook` (an electrosurgical hook that
frees stuck tissue)."""

from .grasper import Grasper
from .hook import Hook
from .paddle import Paddle

__all__ = ["Grasper", "Hook", "Paddle"]
