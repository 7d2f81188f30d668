"""``chunkdic.correlate``: a correlation from its arguments to its result, on one screen.

Paper sections 3–4 (Roux, Hild, Viot, Bernard): the displacement is sought on 8-node
cubic elements, level by level of the ``2^s`` sum pyramid, coarsest first
(:mod:`chunkdic.engine.coarse_to_fine`), each level by modified Gauss–Newton
(:mod:`chunkdic.method`) on passes over the voxels run out of core (:mod:`chunkdic.passes`):
every task reads its own block of ``f`` and the exact window of ``g`` it needs from the store
and returns mesh-sized partials that the client adds up (shared/DESIGN.md, "Out-of-core
shape"). Before anything is written: the inputs (:func:`chunkdic.engine.front.prepare_run`),
the run's identity for resuming (:func:`chunkdic.engine.checkpoint.identify_run`), the plan of
its memory and disk (:mod:`chunkdic.engine.runplan`), the outputs (:mod:`chunkdic.io.outputs`);
then the run's lifecycle (:mod:`chunkdic.engine.lifecycle`).
"""

from __future__ import annotations

from collections.abc import Callable

from ..inputs import memory_target_of
from ..io.outputs import Outputs
from ..method.events import Complete, Event, emit
from ..method.settings import Settings
from ..results.result import Result
from ..scheduler import check_scheduler
from .checkpoint import completed_already, identify_run
from .coarse_to_fine import run_levels
from .front import prepare_run
from .lifecycle import failing, finish, holding, open_levels, run_inputs
from .runplan import make_plan

__all__ = ["correlate", "Settings"]


def correlate(
    ref,
    deformed,
    settings: Settings | None = None,
    *,
    roi=None,
    scheduler=None,
    output=None,
    overwrite: bool = False,
    progress: Callable[[Event], None] | None = None,
    mask=None,
    init=None,
    roi_unit: str | None = None,
    memory_target=None,
    **options,
) -> Result:
    """Measure the displacement field between two scans by multiscale C8-DIC.

    Parameters
    ----------
    ref, deformed : str, Path, ndarray, dask array or zarr array/group
        Reference ``f`` and deformed ``g`` scans (see :func:`chunkdic.open_scan`); shapes
        may differ. Convention: ``f(X) = g(X + u(X))``.
    settings : Settings, optional
        Algorithm settings; keyword ``options`` (any :class:`Settings` field, e.g.
        ``element_size=16``, ``level=2``, ``interpolation="linear"``) override its fields
        or, without ``settings``, make a new one (``element_size`` is then required).
        ``element_size`` may be a physical length, ``"80um"``, converted with the reference's
        voxel size and rounded to whole voxels of ``level``, as ``--element-size`` does
        (:func:`chunkdic.io.units.lengths_in_voxels`; the conversion is logged).
    roi : str or sequence, optional
        ``"z0:z1,y0:y1,x0:x1"`` in level-0 voxels, in ``roi_unit``, or with a unit suffix
        (``"0:500,0:500,0:500um"``); default: the largest centred box of whole elements with
        a small margin. Trimmed to whole elements (reported).
    scheduler : None, "threads", "local[:N]", address or distributed.Client
        Where tasks run (see :func:`chunkdic.scheduler.open_runner`).
    output : path, optional
        Write the result there as a Zarr v3 group; a checkpoint after every iteration
        lets an interrupted run resume (same command, inputs unchanged). One run at a
        time per output (a lock file next to it). An existing output is refused unless
        ``overwrite``, which replaces only a result chunkdic wrote, never an input
        (:mod:`chunkdic.io.outputs`).
    progress : callable, optional
        Called with the record of each stage (:mod:`chunkdic.method.events`: a frozen
        dataclass that reads as a mapping, ``event["stage"]`` = "rigid", "iteration", "level", ...).
    mask : str, Path, array, optional
        Specimen mask of the reference's shape (any input :func:`chunkdic.open_scan`
        reads; non-zero = material): only elements with enough material take part, nodes
        outside are NaN (:mod:`chunkdic.passes.masks`).
    init : str, Path or Result, optional
        An earlier result to start from (a previous step of a loading series, another
        element size, ROI or level), when its gap is lower than no motion's and the rigid
        translation's (docs/engine.md, "The start"): its field is
        evaluated at this run's nodes on the level the run starts on, which is the
        finest level unless ``coarsest`` is given (:mod:`chunkdic.engine.initial`). Checked
        before any output (a result of the same reference shape); recorded in
        ``info["init"]`` and in the resume fingerprint.
    roi_unit : str, optional
        Length unit of a ``roi`` string without suffix (``"um"``), as ``--roi-unit``.
    memory_target : str or int, optional
        Peak resident memory per process to plan for (``"2GiB"`` or bytes; default
        ``chunkdic.memory-target``): blocks and prefilter tasks are sized to fit it
        (:mod:`chunkdic.engine.costs`). A run it cannot hold, or whose scratch or output
        the free disk cannot hold, is refused (:class:`InputError`) before anything is
        written; :func:`chunkdic.plan` shows the plan without running.

    Returns
    -------
    Result
        ``displacement`` (3, nz, ny, nx) float64 in voxels of ``level`` and the rest
        (see :class:`chunkdic.Result`).

    References
    ----------
    Roux, Hild, Viot, Bernard, sections 3 (C8-DIC, multiscale), 4.2 and 5.1 (gap).

    Examples
    --------
    >>> import numpy as np, chunkdic
    >>> rng = np.random.default_rng(0)
    >>> f = rng.random((40, 40, 40)).astype(np.float32)
    >>> g = np.roll(f, 1, axis=0)  # g(x) = f(x - (1, 0, 0))
    >>> res = chunkdic.correlate(f, g, element_size=16, coarsest=0)
    >>> round(float(res.displacement[0].mean()), 3), res.info["status"]
    (1.0, 'converged')
    """
    spec = prepare_run(ref, deformed, settings, roi=roi, roi_unit=roi_unit, init=init, mask=mask, **options)
    identity = identify_run(spec, ref, deformed, mask)
    if output is not None and not overwrite:
        done = completed_already(output, identity.fingerprint)  # the same command re-run on its own complete result
        if done is not None:
            emit(progress, Complete(path=str(output)))
            return done
    budget = make_plan(spec.f_scan, spec.g_scan, spec.meshes, spec.settings, scheduler=scheduler, output=output,
                       target=memory_target_of(memory_target))
    budget.check()  # memory target and free disk: refused before anything is written
    outputs = entry = None
    if output is not None:  # every output rule (chunkdic.io.outputs), nothing written yet
        outputs = Outputs(inputs=run_inputs(spec, ref, deformed, mask), overwrite=overwrite)
        entry = outputs.add(output, "result", resumable=True)
    check_scheduler(scheduler)  # an unreachable or foreign address: refused before anything is written
    with holding(spec, identity, budget, output, outputs, entry, scheduler, progress) as held:
        with failing(held):
            result = run_levels(*open_levels(held, budget, progress))
        return finish(result, held, ref, deformed, mask)
