"""The viewport worker's cache convergence: the final renders' stored-hit solver
(`hybridgi_core.solver.GISolver`), run one short step at a time (worker thread only, pure numpy).

Why not the EMA updater: with hysteresis 0.9 every update adds one bounce but blends it in at a
tenth, so a multi-bounce cache needs ~60 updates per cell to reach 97% of its light (Cornell box),
and the viewport used to stop after 24 (Diffuse Indirect ~20-25% low, the image ~13% dark). The
solver's fixed point over stored hits has no such lag: one traced batch and a handful of
iterations give the converged cache, each later batch refines it, and a lamp, material or world
edit re-shades the stored hits and solves again without a probe ray; a geometry edit retraces
only the stored rays whose segments meet the changed boxes (`GISystem.invalidate_boxes`).

Every call of `step` does one unit of work, so that the worker looks at its inbox between units
(a new view or edit is never queued behind a whole convergence):

    begin + trace batch 0  ->  relax ... relax (one iteration a step)  ->  tail + neighbour filter
    -> trace batch 1  ->  relax ...  -> ... until `batches` batches are traced: done

Events restart the relax phase from the stored hits. A lamp, material or world edit re-shades
the stored hits one batch a step (`GISolver.relight_batch`: shadow rays only, batch 0 first, the
sources from the batches done so far), solving after each; a geometry edit retraces the stale
rays (`resolve`), then iterations as above.
"""

from __future__ import annotations

import time

import numpy as np

#: Iterations of one solve at most (the solver stops sooner once converged).
MAX_ITERATIONS = 16
#: Probe rays of one step of a refining batch (`MORE`, traced in parts of this many rays, so a
#: lamp or camera edit waits for one part, ~0.1-0.3 s on 2 cores, not for a whole batch's 1-2 s).
MORE_PART_RAYS = 2 * 98304
#: Fewest chunks of a traced batch (`GISolver.min_chunks`): fixed, so the viewport's cache is the
#: same whatever its pool's thread count, and a small batch still feeds up to this many threads.
MIN_CHUNKS = 4

# Phases of the schedule.
BEGIN, RESOLVE, RELIGHT, RELAX, MORE, DONE = "begin", "resolve", "relight", "relax", "more", "done"


def relight_order(solver) -> list[int]:
    """The order `relight_batch` re-shades a solver's batches in: the complete batch (one that
    holds every solver cell) with the fewest stored rays first (the viewport's short first
    batch: half the shadow rays of a full one before the first re-lit image), then the batch that
    carries the bounces, then the rest in order. The first must be complete: the first solve's
    sources come from it alone, and the bounces (A x, read at the bouncing batch's hits, not their
    lamp light) need a source for each of their cells; a batch still being traced in parts is not."""
    rays, cells = {}, {}
    for c in solver.chunks:
        rays[c.batch] = rays.get(c.batch, 0) + c.rays
        cells[c.batch] = cells.get(c.batch, 0) + c.cells.size
    batches = list(range(solver.batches))
    complete = [b for b in batches if cells.get(b, 0) >= solver.cells.size] or [solver.bounce_from]
    first = min(complete, key=lambda b: (rays.get(b, 0), b != solver.bounce_from, b))
    rest = [solver.bounce_from] if solver.bounce_from != first else []
    return [first] + rest + [b for b in batches if b not in (first, solver.bounce_from)]


class SolveSchedule:
    """Where the worker's cache stands on its way to the converged fixed point.

    batches : traced direction batches to refine to while the view holds still (the first
        converged image comes from the first one)
    first_rays : directions per cell of the first batch (None: rays_per_cell)
    """

    def __init__(self, batches: int, first_rays: int | None = None):
        self.batches = max(1, int(batches))
        self.first_rays = first_rays
        self.system = None
        self.phase = BEGIN
        self.iterations = 0
        self._filter_direct = True  # the direct band was re-blended: filter it with the next tail
        self._relight_next: int | None = None  # next batch to re-shade after a shading edit
        self._relight_part = 0  # its next part (`relight_batch(part=)`)
        self._materials = False  # the re-shade includes materials and the world (not lamps only)
        self.solved_once = False  # a solve of the current hits converged (cells count as settled)
        self._clean = False  # nothing changed the cache since it was last solved and filtered
        self._fresh_at: float | None = None  # when a fresh cache's first batch began (till solved)
        #: The refining batch traced in parts: (batch, its cells, cells traced so far), or None.
        self._pending: tuple[int, np.ndarray, int] | None = None
        self.steps_ms: dict[str, float] = {}
        #: Steps that may have moved the depth moments: those that trace or retrace batch 0's rays
        #: (`_geometry_bands` takes depth from the first batch only). Re-shades, refining batches,
        #: iterations and the filter change the SH texture only, so its depth is not packed again
        #: (~0.1-0.2 s a pack on 2 busy cores, after every refining batch before).
        self.blends = 0
        #: Bumped by every event that changes the light the cache estimates (a new system, a
        #: shading or geometry event, new cells to cover), not by refining batches: the viewport's
        #: pixel passes over one epoch stay valid while the cache refines.
        self.epoch = 0
        #: When the last event (`changed`) began a re-solve.
        self.changed_at = 0.0

    # --- events ---------------------------------------------------------------------------------

    def attach(self, system) -> None:
        """A (new) system: a new one starts over from batch 0 (its solver has no hits)."""
        if system is not self.system:
            self.system = system
            self.epoch += 1
            if system is not None:
                system.solver.min_chunks = MIN_CHUNKS
            self.phase = BEGIN
            self.solved_once = self._clean = False
            self._fresh_at = None
            self._pending = None

    def changed(self, shading: bool, geometry: bool, materials: bool = True) -> None:
        """The session raised events on the stored hits: solve again from them.

        shading : lamps, world or materials changed; materials : the world or materials did
            (the geometry bands and albedo re-shade too), else lamps only (shadow rays only)
        geometry : stored rays turned stale (`invalidate_boxes`)
        """
        if self.phase == BEGIN or self.system is None or not (shading or geometry):
            return
        self.solved_once = False
        self.epoch += 1
        self.changed_at = time.perf_counter()
        if shading:
            self._materials = materials or (self._relight_next is not None and self._materials)
            self._relight_next = 0
            self._relight_part = 0
            self._filter_direct = self._filter_direct or materials
        # A geometry event re-shades every stale hit in one go (`resolve`), lamps included.
        self.phase = RESOLVE if geometry or self.phase == RESOLVE else RELIGHT
        if geometry:
            self._relight_next = None
            self._filter_direct = self._filter_direct or shading

    def cover(self, cells: np.ndarray) -> None:
        """Make sure the solver holds `cells` (the view's): new ones are traced by a resolve."""
        solver = self.system.solver if self.system is not None else None
        if solver is None or self.phase == BEGIN or cells.size == 0:
            return
        missing = np.setdiff1d(cells, solver.cells, assume_unique=False)
        if missing.size:
            solver.extend(missing)
            self.phase = RESOLVE
            self.epoch += 1

    # --- work -----------------------------------------------------------------------------------

    def holding(self, hold_s: float) -> bool:
        """Whether a fresh cache's first solve (batch 0 traced, not yet converged) began less than
        hold_s ago: its iterates are too dark to be worth publishing (`worker.FIRST_SOLVE_HOLD_S`)."""
        return self._fresh_at is not None and time.perf_counter() - self._fresh_at < hold_s

    @property
    def first_solve(self) -> bool:
        """A fresh cache's first solve is under way (batch 0 traced or being traced, not yet
        converged): the first converged image is what the view waits for."""
        return self.system is not None and not self.solved_once and (self._fresh_at is not None or self.phase == BEGIN)

    @property
    def refining(self) -> bool:
        """A refining batch is traced in part (`MORE`), or traced and not yet solved."""
        return self._pending is not None or (self.phase == RELAX and self._filter_direct and self.solved_once)

    @property
    def stable(self) -> bool:
        """The cache has converged over its current hits and nothing changed it since: what it
        estimates holds until the next event (refining batches may follow: `refinable`). After a
        shading edit that is once the first re-shaded batch has solved: the batches still to
        re-shade refine that estimate as refining batches do (the first view's pixel passes are
        traced over its first batch's solve too), and so does the rest of a refining batch the
        edit cut short (its traced part is in the solved, filtered cache)."""
        return self.system is not None and self.solved_once and self._clean and self.phase in (MORE, DONE, RELIGHT)

    @property
    def refinable(self) -> bool:
        """Converged, with refining work left (a batch to trace or the rest of one, batches to
        re-shade) and no re-shade half done: it may wait for the view's own light."""
        return self.stable and self.phase in (MORE, RELIGHT) and self._relight_part == 0

    @property
    def reshaded(self) -> bool:
        """Every batch is re-shaded since the last shading edit (or none came): the batches after
        the first re-shaded one re-shade as a refinement (`stable`), which the viewport's pixel
        passes are traced again over."""
        return self._relight_next is None

    @property
    def has_work(self) -> bool:
        return self.system is not None and self.phase != DONE

    def step(self, cells: np.ndarray) -> int:
        """One unit of work towards the converged cache; `cells` the view's visible cells.
        Returns the probe rays traced."""
        system = self.system
        solver = system.solver
        t0 = time.perf_counter()
        rays = 0
        phase = self.phase
        # Every step but a lamps-only re-shade (stored hits only) changes the cache; `_finish`
        # leaves it solved and filtered again.
        self._clean = self._clean and phase == RELIGHT and not self._materials
        if phase == BEGIN:
            solver.begin(np.union1d(system.surface_cells(), cells))
            rays = solver.trace_batch(0, rays=self.first_rays).rays
            self._fresh_at = time.perf_counter()
            self._filter_direct = True
            self.phase, self.iterations = RELAX, 0
        elif phase == RESOLVE:
            solver.extend(system.surface_cells())  # moved surfaces read new cells (`move_dynamic`)
            # One iteration with the retrace / re-shade; the rest one per step.
            st = solver.resolve(max_iterations=1)
            self._relight_next = None  # every stale hit re-shaded
            self._pending = None  # resolve traced the rest of a batch in parts too (its missing cells)
            rays = st.rays
            self.phase, self.iterations = RELAX, 1
            if solver.converged:
                self._finish()
        elif phase == RELIGHT:
            # One part of a batch a step (an edit waits for a part); a solve after each batch.
            batch = relight_order(solver)[self._relight_next]
            rays = sum(c.rays for c in solver.chunks if c.batch == batch)
            parts = max(1, -(-rays // MORE_PART_RAYS))
            solver.relight_batch(batch, materials=self._materials, part=(self._relight_part, parts))
            self._relight_part += 1
            if self._relight_part >= parts:
                self._relight_part = 0
                self._relight_next += 1
                if self._relight_next >= solver.batches:
                    self._relight_next = None
                self.phase, self.iterations = RELAX, 0
        elif phase == RELAX:
            solver.relax()
            self.iterations += 1
            if solver.converged or self.iterations >= MAX_ITERATIONS:
                self._finish()
        elif phase == MORE:
            if self._pending is None:
                self._pending = (solver.batches, solver.cells, 0)
            batch, todo, done = self._pending
            per_part = max(1, MORE_PART_RAYS // max(1, system.cache.settings.rays_per_cell))
            rays = solver.trace_batch(batch, todo[done : done + per_part], first_chunk=done).rays
            done += per_part
            self._filter_direct = True  # the batches' mean replaced the filtered direct band
            if done < todo.size:
                self._pending = (batch, todo, done)
            else:
                self._pending = None
                if self.first_rays is not None and solver.bounce_from == 0:
                    # A full batch now carries the bounces (less noise in A than the first one's).
                    solver.bounce_from = batch
                self.phase, self.iterations = RELAX, 0
            solver.prepare()  # this part's lookups now, not all of them in the next iteration
        if phase in (BEGIN, RESOLVE):
            self.blends += 1
        self.steps_ms[phase] = (time.perf_counter() - t0) * 1e3
        return rays

    def _finish(self) -> None:
        """The geometric tail, the neighbour filter, sample counts; then more batches or done."""
        system = self.system
        solver = system.solver
        solver.extrapolate()
        bands = ("sh_indirect", "sh_direct") if self._filter_direct else ("sh_indirect",)
        solver.filter_cells(bands=bands)
        self._filter_direct = False
        # Converged cells count as such for whatever reads the sample counts (the Cache Cells
        # colours, an EMA update that follows): at least the EMA's window.
        cache = system.cache
        window = int(np.ceil(1.0 / max(1.0 - cache.settings.hysteresis, 1e-3)))
        c = solver.cells
        cache.samples[c] = np.where(cache.samples[c] > 0, np.maximum(cache.samples[c], window), 0)
        cache.version += 1
        self.solved_once = True
        self._clean = True
        self._fresh_at = None
        if self._relight_next is not None:
            self.phase = RELIGHT
        else:
            self.phase = MORE if self._pending is not None or solver.batches < self.batches else DONE
