"""The real-time simulator (``esmm simulate``); see docs/simulate.md.

Modules: :mod:`.kernels` (numba hot loops), :mod:`.integrator` (force model,
stability bound, mass scaling, :class:`~.integrator.Simulator`, FIRE),
:mod:`.scene` (scene files), :mod:`.grasper` (grasp planning),
:mod:`.history` (HDF5 + XDMF), :mod:`.render` (off-screen video),
:mod:`.run` (``simulate`` / ``simulate_network``). Nothing heavy is imported here.
"""
