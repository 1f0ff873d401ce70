"""The ROS 2 layer: ``cloth_node`` (:mod:`.node`) and what it is made of: parameters
(:mod:`.params`), command parsing (:mod:`.commands`), tick pacing (:mod:`.pacing`) and
numpy <-> message conversions (:mod:`.conversions`)."""
