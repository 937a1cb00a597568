"""Every moving trajectory's model by name: the vehicles and hand motions (``magnet.simulator.motion``), the walks
(``magnet.simulator.walks``) and the planar vehicles (``magnet.simulator.ground``) and the hand-held wand
(``magnet.simulator.wand``)."""

from __future__ import annotations

from magnet.simulator import ground, motion, walks, wand
from magnet.simulator.motion import MotionModel

#: trajectory name -> model class
MODELS: dict[str, type[MotionModel]] = {**motion.MODELS, **walks.MODELS, **ground.MODELS, **wand.MODELS}
