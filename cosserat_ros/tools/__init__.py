"""The executables and make targets beside the node: ``record`` and ``render``
(:mod:`.record`, :mod:`.render`), ``make bench`` (:mod:`.bench`, with the MuJoCo peer of
:mod:`.peer_mujoco`) and ``make validate`` (:mod:`.validate`)."""
