"""Instruments: what acts on the tissue of a :class:`heml_gym.World`, one object per instrument
standing for it in every world of the batch, each owning its slice of the action, its part
of the observation and its ``info`` entries. Today: :class:`Grasper`."""

from .grasper import Grasper

__all__ = ["Grasper"]
