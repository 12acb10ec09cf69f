"""Physics checks against closed-form answers (ROS-free, like :mod:`..core` and :mod:`..haptics`):
:mod:`.analytic` holds the reference solutions, :mod:`.cases` the set-ups that measure the solver
against them. Used by the test suite and by ``benchmarks/validate.py``."""
