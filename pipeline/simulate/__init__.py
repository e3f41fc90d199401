"""The real-time simulator (``esmm simulate``); see docs/guide/simulate.md and docs/design/simulator.md.

Modules, bottom up (each imports only those above it in this list):

* :mod:`.kernels`: everything compiled: the spring term's force pass (the
  material effects a compile-time option), the step loop (written once,
  compiled serial and parallel), the grasper, the floor, FIRE;
* :mod:`.effects`: material effects' parameters and per-spring state;
* :mod:`.springterm`: :class:`~.springterm.SpringTerm`, the spring force term
  and the bounds of its tangent;
* :mod:`.model`: :class:`~.model.Model` (constant), :class:`~.model.State`
  (mutable), :class:`~.model.Control` (the grasper), the
  :class:`~.model.ForceTerm` interface, :class:`~.model.Floor`, :class:`~.model.Grasp`;
* :mod:`.stepper`: the :class:`~.stepper.Stepper` interface, the explicit
  :class:`~.stepper.SymplecticEuler`, the stability bound, mass scaling and the
  per-frame :class:`~.stepper.StepSchedule`;
* :mod:`.relax`: quasi-static equilibrium (FIRE);
* :mod:`.simulator`: :class:`~.simulator.Simulator`, the session holding them together;
* :mod:`.scene` (scene files), :mod:`.grasper` (grasp planning), :mod:`.history`
  (HDF5 + XDMF), :mod:`.render` (off-screen video), :mod:`.plots` (force plot);
* the implicit stepper, :class:`~.implicit.BackwardEuler` (:mod:`.implicit`), a thin stepper
  over its parts: :mod:`.implicit_stats` (its statistics and threads), :mod:`.contact` (the
  floor's active set), :mod:`.implicit_system` (one step's system), :mod:`.factorcache` (the
  reused factor), :mod:`.haptics` (the grasper force between solves) and
  :mod:`.implicit_iteration` (the solve);
* :mod:`.runsetup` (a run's setup), :mod:`.frames` (its frame loop),
  :mod:`.summary` (its figures), :mod:`.run` (``simulate`` / ``simulate_network``).

Nothing heavy is imported here.
"""
