"""The simulator core: no ROS import.

Reading order: :mod:`.model` and :mod:`.state` (what is stored), one term in
:mod:`.terms` (how physics is written), :mod:`.solvers` (how it moves),
:mod:`.simulator` (the ``ClothSimulator`` facade).
"""
