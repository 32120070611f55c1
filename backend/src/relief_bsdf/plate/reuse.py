"""What the deterministic engine keeps between evaluations, through the memory owner (`plate.memory`):
solvers held by their tables' content and plate, found before any table is derived (`held_for_request`),
reused when only the instrument, the bulk or the outside table changed (`_reused_solver`), and the sector
table let go once its kernels exist (`drop_sector_table`).  The numbers are always those of a fresh solver."""
from __future__ import annotations

import copy
from typing import Any

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.plate.sector_loop import SectorsHeader
from relief_bsdf.plate.setup import BULK_FIELDS, EngineSetup, plate_key
from relief_bsdf.plate.solver import PlateSolver


def _note_request(memory: Any, request: tuple | None, solver: PlateSolver, half: PlateSolver | None) -> None:
    """Mark the held solver (and its half-turned one) as the answer to `request` (`held_for_request`)."""
    key = getattr(solver, "memory_key", None)
    held = memory.peek(key) if request is not None and key is not None else None
    if held is None:
        return
    half_key = getattr(half, "memory_key", None) if half is not None else None
    if half is not None and half_key is None:
        return
    held.requests = {**getattr(held, "requests", {}), request: half_key}


def held_for_request(memory: Any, request: tuple, model: EngineSetup) -> PlateSolver | None:
    """A solver for `model` on the tables of `request`, from a held solver made for that request (the same
    plate: a copy carrying the new instrument; another bulk: the tables' part shared, `_reused_solver`),
    or None.  The tables' keys count as used (`ForwardMemory.note_used`), as if they had been asked for."""
    plate = plate_key(model)
    found = [(key, held, getattr(held, "requests", {})[request]) for key, held in memory.entries("solver")
             if request in getattr(held, "requests", {})]
    for exact in (True, False):              # the same plate first, then another bulk (as `_reused_solver`)
        for key, held, half_key in reversed(found):
            main = _answer(memory, key, held, half_key, model, plate, exact)
            if main is not None:
                _note_request(memory, request, main, main.half_turn)
                return main
    return None


def _answer(memory: Any, key: tuple, held: PlateSolver, half_key: tuple | None, model: EngineSetup, plate: tuple,
            exact: bool) -> PlateSolver | None:
    """`held_for_request`'s solver from one held solver and its half-turned one, or None."""
    if (key[2] == plate) != exact:
        return None
    half = None
    if half_key is not None:
        half = memory.peek(half_key)
        if half is None or (half_key[2] == plate) != exact:
            return None
    main = _variant(memory, key, held, model, plate)
    if main is None:
        return None
    main.half_turn, main.turned = None, {}
    if half is not None:
        half = _variant(memory, half_key, half, model, plate)
        if half is None:
            return None
        half.half_turn, half.turned = None, {}
        main.half_turn = half
        memory.note_used([t for t in half_key[1] if t is not None and t[0] != "object"])
    memory.note_used([t for t in key[1] if t is not None and t[0] != "object"])
    return main


def _variant(memory: Any, key: tuple, held: PlateSolver, model: EngineSetup, plate: tuple) -> PlateSolver | None:
    """The held solver `held` (under `key` = ("solver", tokens, plate)) for `model`: a copy when the plate is
    the same, a kept copy sharing the tables' part when only the bulk differs, else None."""
    if key[2] == plate:
        memory.touch(key)
        new = copy.copy(held)
        new.model = model
        return new
    if tuple(kv for kv in key[2] if kv[0] not in BULK_FIELDS) == tuple(kv for kv in plate if kv[0] not in BULK_FIELDS):
        new = copy.copy(held)
        new.model, new._ops = model, {}
        return _kept(memory, key[1], plate, new)
    return None


def drop_sector_table(solver: PlateSolver) -> None:
    """Once a solver's sector kernels exist for the wavelengths it solved, its inside sector table (the
    largest table of an evaluation, as large as the kernels) is let go: the solver and the held solver it
    was copied from keep a `SectorsHeader`, the memory owner discards the table and adds what it cost
    to the held solver's cost (evicting that solver now costs the table too).  Later solvers on the same
    tables come from `held_for_request` without it; one that needs it again derives it again."""
    t = solver.inside_sectors
    if t is None or isinstance(t, SectorsHeader):
        return
    memory = current_memory()
    header = SectorsHeader.of(t)
    table_key = memory.key_of(t)
    cost = memory.cost_of(table_key) if table_key is not None else 0.0
    for s in (solver, solver.half_turn, *getattr(solver, "turned", {}).values()):
        if s is None:
            continue
        key = getattr(s, "memory_key", None)
        for obj in (s, memory.peek(key) if key is not None else None):
            if obj is not None and obj.inside_sectors is t:
                obj.inside_sectors = header
        if key is not None and cost:
            memory.refresh(key, cost)
            cost = 0.0
    if table_key is not None:
        memory.discard(table_key)



def _table_token(memory: Any, table: BsdfTable | None) -> tuple | None:
    """What names a table in a solver's key: the memory owner's key of it (its content), else the object
    itself (a table the caller made: the solver holds it, so its id is not reused while the solver is held)."""
    if table is None:
        return None
    return memory.key_of(table) or ("object", id(table))


def _reused_solver(model: EngineSetup, inside: BsdfTable, outside: BsdfTable | None,
                   back: BsdfTable | None, sectors: BsdfTable | None = None, keep: bool = True) -> PlateSolver:
    """A PlateSolver whose per-wavelength operators (round-trip system, exit maps) are those of an
    earlier solver on the same tables (by content: the memory owner's keys) and the same plate
    (thickness, indices, bulk, grid): they do not depend on the instrument (source polarisation,
    cone, blur, tilt, stray light), which acts only on the incident Stokes vector and the detector
    reading.  A fit or diagnosis that changes only the instrument then reuses them.  Short of that:
    the same tables with another bulk (absorption, thickness, volume scattering) share the tables'
    part (`PlateSolver._table_ops`); another outside table on the same loop tables and plate (a tilt)
    shares the loop's operators (`PlateSolver.with_outside`).  The numbers are always those of a fresh
    solver.  A new solver is held by the memory owner (`plate.memory`, kind "solver") unless `keep` is
    False; `run` measures it again once it has solved."""
    memory = current_memory()
    plate = plate_key(model)
    tokens = tuple(_table_token(memory, t) for t in (inside, outside, back, sectors))
    held = [(k[1], k[2], v) for k, v in memory.entries("solver")]          # (tokens, plate, solver), oldest first
    for t, key, solver in reversed(held):
        if t == tokens and key == plate:
            memory.touch(("solver", t, key))
            new = copy.copy(solver)          # shares the operators (solver._ops), carries the new instrument
            new.model = model
            return _with_sectors(new, sectors)
    tabs = tuple(kv for kv in plate if kv[0] not in BULK_FIELDS)
    for t, key, solver in reversed(held):     # the same tables, another bulk (an absorption)
        if t == tokens and tuple(kv for kv in key if kv[0] not in BULK_FIELDS) == tabs:
            new = copy.copy(solver)
            new.model, new._ops = model, {}        # the bulk's part anew, the tables' part (solver._tops) shared
            return _kept(memory, tokens, plate, _with_sectors(new, sectors), keep)
    for t, key, solver in reversed(held):     # same loop tables, another outside table (a tilt)
        if (key == plate and t[0] == tokens[0] and t[2] == tokens[2] and t[3] == tokens[3] and outside is not None
                and t[1] is not None and outside.is_polarized == solver.outside.is_polarized):
            return _kept(memory, tokens, plate, _with_sectors(solver.with_outside(model, outside), sectors), keep)
    return _kept(memory, tokens, plate, PlateSolver(model, inside, outside, back=back, inside_sectors=sectors), keep)


def _with_sectors(solver: PlateSolver, sectors: BsdfTable | None) -> PlateSolver:
    """`solver` with the sector table it was asked for (a held solver may keep only its `SectorsHeader`)."""
    if sectors is not None and isinstance(solver.inside_sectors, SectorsHeader):
        solver.inside_sectors = sectors
    return solver


def _kept(memory: Any, tokens: tuple, plate: tuple, solver: PlateSolver, keep: bool = True) -> PlateSolver:
    """Hold `solver` in the memory owner under its tables' tokens and plate (not when `keep` is False).

    A solver made by copying a held one (another bulk, another outside table) starts answering no request
    (`held_for_request`): the requests its original answered name the original's tables, not its own."""
    solver.requests = {}
    if keep:
        memory.put(("solver", tokens, plate), solver, "solver")
        solver.memory_key = ("solver", tokens, plate)
    return solver


def refresh_solver(solver: PlateSolver, cost_s: float = 0.0) -> None:
    """Measure a held solver again after it solved (its operators are made lazily), add what the solve
    cost, and evict to the budget."""
    key = getattr(solver, "memory_key", None)
    if key is not None:
        current_memory().refresh(key, cost_s)
