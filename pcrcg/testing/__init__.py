"""Fixtures for tests and benchmarks: tiny synthetic data made in memory (or in a temporary folder),
never used by a run (the real data generator is :mod:`pcrcg.data.synth`).

* :mod:`pcrcg.testing.rooms`: :func:`~pcrcg.testing.rooms.box_room`, the one box room of the fixtures
  (points and colors of a room with boxes on the floor);
* :mod:`pcrcg.testing.pairs`: pairs and problems cut from it: ``toy_pair`` (a :class:`PairSample` of
  two crops, for the models), ``make_fragment_pair`` and ``simulate_outputs`` (fragments with outputs
  that behave like a trained network's, for registration and evaluation), ``correspondence_problem``
  (RANSAC's input);
* :mod:`pcrcg.testing.layouts`: ``write_layout``, a tiny data set in the 3DMatch layout on disk;
* :mod:`pcrcg.testing.scenes`: a ray-cast RGB-D box room with known geometry and ``make_pair``, a
  :class:`PairSample` of two fused fragments with their views (lifting, 2D vision).

Fragments are voxelised with the real fragment step, :func:`pcrcg.data.fusion.voxel_average`.
Nothing in :mod:`pcrcg` that a run uses imports this package.
"""
