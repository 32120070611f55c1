"""`PlateSolver`: the plate operator of one pair of boundary tables (the method: `plate.deterministic`'s module
doc).  Per wavelength the round-trip system is factorised once (`_operators`) and every incidence solved
with it (`solve`): first-face scattering of the source, the delta-beam chain, the diffuse loop in
azimuthal modes, the exits through both faces.  The loop by azimuth sector of an anisotropic relief is
`plate.sector_loop`, the slab's coupling `plate.coupling`, how a table is sampled `plate.tableview`."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.errors import InputError
from relief_bsdf.parallel.blas import blas_single_thread   # the plate's matrices are small (N ~ 90): one thread
from relief_bsdf.plate.coupling import _beam_extinction, _slab_sources, _slab_system
from relief_bsdf.plate.detector import DirectField, centre_values
from relief_bsdf.plate.memory import current_memory
from relief_bsdf.plate.modes import _block_diag, _blocks, _exit_modes, _loop_solve, _reflect_up, _rough_exit
from relief_bsdf.plate.sector_loop import SectorLoop
from relief_bsdf.plate.setup import EngineSetup
from relief_bsdf.plate.tableview import _fresnel, _lin_matrix, _snell_deg, _TableView


@dataclass
class PlateResult:
    """Plate BSDF of one incidence on the outgoing grid, plus the delta beams.

    grid_R / grid_T: (T, A) BSDF (1/sr) at theta_out_deg x delta_deg (delta = outgoing
    azimuth minus the incident beam's propagation azimuth phi_i + 180).
    deltas: list of (side, theta_deg, delta_deg, power fraction) for exact beams.
    direct / loop_R / loop_T: when the outside table is finer than the engine grid, the direct
    reflection and the first transmitted pass on the table's own cells (read by integrating them
    over the detector cone) and the rest on the engine grid; grid_R / grid_T hold the sum.
    """

    wavelength_nm: float
    theta_i_deg: float
    phi_i_deg: float
    theta_out_deg: np.ndarray
    theta_edges_deg: np.ndarray
    delta_deg: np.ndarray
    grid_R: np.ndarray
    grid_T: np.ndarray
    deltas: list = field(default_factory=list)
    direct: Any = None            # DirectField of the outside table's direct parts (or None)
    loop_R: Any = None            # with `direct`: grid_R / grid_T without the direct parts (engine grid)
    loop_T: Any = None

    def hemispherical(self) -> dict:
        """Directional-hemispherical R and T of the plate (diffuse + delta)."""
        da = 360.0 / self.delta_deg.size
        psa = projected_solid_angle(self.theta_edges_deg, [0.0, da])[:, 0]
        out = {}
        for side, g in (("R", self.grid_R), ("T", self.grid_T)):
            d = float(np.sum(g * psa[:, None]))
            s = float(sum(p for sd, _, _, p in self.deltas if sd == side))
            out[side] = d + s
            out[f"diffuse_{side}"] = d
            out[f"specular_{side}"] = s
        return out


class PlateSolver(SectorLoop):
    """Plate operator for one pair of boundary tables; call `solve` per wavelength and incidences.

    Per wavelength the round-trip system is factorised once and reused for every incidence.
    """

    def __init__(self, model: EngineSetup, inside: BsdfTable, outside: BsdfTable | None = None,
                 back: BsdfTable | None = None, front: tuple[BsdfTable, BsdfTable] | None = None,
                 inside_sectors: BsdfTable | None = None):
        """`back`: optional BSDF table (light from inside) of the second, back face; None = flat.

        `inside_sectors`: the relief's inside table by incidence-azimuth sector (an anisotropic relief,
        `plate.faces.inside_sectors`; with a sector at 0 deg the inside table serves no light of the
        loop); the light inside the plate (every order of the loop: the second pass and the trapped
        light) then scatters and leaves through the sector nearest its azimuth
        (`_sector_loop`, `_sector_exits`).

        `front`: optional (outside, inside) tables of the FRONT face when the relief is on the back
        (None = flat).  The plate is then solved with the roles swapped: the front face is the first
        face (both tables) and the relief the second face, which light reaches only from inside
        (`inside` is the relief's inside table), i.e. exactly the front-relief-plus-back-table system.
        """
        if front is not None:
            if model.rough_face != "back":
                raise InputError("plate", "a BSDF table for the front face needs the relief on the back face "
                                 "(with the relief in front, give the second face as `back`)")
            if back is not None:
                raise InputError("plate", "with the relief on the back face, the second face is the relief: "
                                 "give the front face as `front`, not `back`")
            f_out, f_in = front
            model, back = replace(model, rough_face="front"), inside
            outside, inside = f_out, f_in
        if back is not None:
            if model.rough_face != "front":
                raise InputError("plate", "a BSDF table for the second face is supported when the relief is on "
                                 "the front face (the back face is then the second face)")
            if back.incident_from != "inside":
                raise InputError("plate", "the back-face table must have incident_from = 'inside'")
        self.back = back
        self.inside_sectors = inside_sectors
        if inside_sectors is not None and (model.rough_face != "front" or inside_sectors.incident_from != "inside"):
            raise InputError("plate", "inside sector tables need the relief on the front face and incident_from "
                             "= 'inside'")
        if inside.incident_from != "inside":
            raise InputError("plate", "the inside table must have incident_from = 'inside'")
        if model.rough_face == "front":
            if outside is None:
                raise InputError("plate", "a relief on the front face needs the outside table too")
            if outside.incident_from != "outside":
                raise InputError("plate", "the outside table must have incident_from = 'outside'")
        self.model = model
        self.inside = inside
        self.outside = outside
        self.mueller = model.stokes_loop and (inside.is_polarized or (outside is not None and outside.is_polarized)
                                              or (back is not None and back.is_polarized))
        self.theta_edges = np.asarray(inside.theta_s_edges_deg, float)
        self.theta_c = 0.5 * (self.theta_edges[1:] + self.theta_edges[:-1])
        A = int(model.azimuth_cells)
        self.delta = np.arange(A) * (360.0 / A)
        self.psa = projected_solid_angle(self.theta_edges, [0.0, 360.0 / A])[:, 0]        # (N,)
        self._ops: dict = {}
        self._tops: dict = {}          # the tables' part of the operators (`_table_ops`), shared across bulks
        self._twins: dict = {}         # wavelength -> the one solved in its place (`_twin_wavelength`)
        # the solver on the outside table of the relief turned by a half turn, for the rows lit from the
        # far half of azimuths (`far_side`, `plate.faces.half_turned_outside`; set by `solver_of`), or None:
        # those rows are then read from this solver's phi_i = 0 table turned by their azimuth
        self.half_turn: "PlateSolver | None" = None
        # solvers on the outside tables of the relief lit from other incidence azimuths (ray-traced reliefs,
        # `plate.deterministic.turned_tables`; set by `solver_of`): azimuth (deg, `rows.azimuth_key`) -> solver
        self.turned: dict = {}

    def memory_parts(self) -> tuple:
        """What this solver holds (`plate.memory.deep_buffers`): its tables, its operators and their factors,
        the tables' part it may share with solvers of another bulk, the fields kept per wavelength.  The
        memory owner counts each buffer once over all its entries (a table it holds itself, the tables'
        part two solvers share); the half-turned and turned solvers are entries of their own."""
        return (self.inside, self.outside, self.back, self.inside_sectors, self._ops, self._tops, self._twins)

    # -- per wavelength operators
    def _table_ops(self, wl: float) -> dict:
        """The part of a wavelength's operators that the boundary tables and the indices fix (the
        kernels in azimuthal modes, the faces' delta parts and exit maps); the bulk (thickness,
        absorption, volume scattering) acts through `_operators` alone.  Shared by the solvers of
        one plate's tables whose bulk differs (`_reused_solver`: a fit of the absorption)."""
        if wl in self._tops:
            return self._tops[wl]
        m = self.model
        n = float(np.real(m.index.n(wl)))
        n0 = float(np.real(m.outside_index.n(wl)))
        tc = self.theta_c
        N = tc.size
        c = 4 if self.mueller else 1
        mv = (n, n0) if m.inside_interpolation == "moving" else None
        vin = _TableView(self.inside, wl, self.mueller, "inside table", mv)
        # Fresnel of the flat face averaged over each internal cell (projected solid angle): the cell
        # straddling the critical angle then loses exactly what the exit remap below lets out
        e = np.radians(self.theta_edges)
        nsub = 64
        u = (np.sin(e[:-1])[:, None] ** 2 + (np.arange(nsub) + 0.5)[None] / nsub
             * (np.sin(e[1:]) ** 2 - np.sin(e[:-1]) ** 2)[:, None])
        cos_sub = np.sqrt(np.clip(1.0 - u, 0.0, 1.0))
        RF = _fresnel(cos_sub, n, n0, "R").mean(axis=1)                                     # (N, 4, 4)
        vB = _TableView(self.back, wl, self.mueller, "back-face table", mv) if self.back is not None else None
        th_sub = np.degrees(np.arccos(cos_sub))                                             # cell average too
        if vB is not None:
            RF = vB.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1)            # its delta part
        # the rough face's own delta part acting on diffuse light from inside: specular reflection
        # keeps the cell (and the propagation azimuth), so it is diagonal in every azimuthal mode
        # (times 1 - 1e-9: between two lossless specular faces a totally reflected cell would make the
        # loop singular; it is fed nothing, and 1e-9 per round trip stands for the plate's finite size)
        SR = vin.specular_many("R", th_sub).reshape(N, nsub, 4, 4).mean(axis=1) * (1 - 1e-9)  # (N, 4, 4)
        Kh = self._loop_kernel(vin, c)                                                      # (T, J, M[,4,4])
        KBh = GBT = None
        if vB is not None:
            KBh = np.moveaxis(vB.diffuse_modes("R", tc, tc, self.delta), 0, 1)
            KBh *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
            GBh = vB.diffuse_modes("T", tc, tc, self.delta, detector_row=True)
            GBT = (np.moveaxis(GBh, 2, 0) if c == 1 else np.moveaxis(GBh, (2, 3), (0, 2))).reshape(
                GBh.shape[2], -1, GBh.shape[1])
        GhT, Wflat, Wspec = self._exit_maps(vin, vB, n, n0, c)
        sector_kernels = None
        if self.inside_sectors is not None and vB is None and m.rough_face == "front":
            current_memory().reserve(_sector_bytes(self.inside_sectors, N, c, Kh.shape[2],
                                                   np.asarray(self.inside.theta_i_deg).size))
            sector_kernels = self._sector_kernels(wl, c, mv, vin, Kh, GhT)
        t = dict(n=n, n0=n0, c=c, vin=vin, vB=vB, RF=RF, SR=SR, Kh=Kh, KBh=KBh, GBT=GBT, GhT=GhT,
                 Wflat=Wflat, Wspec=Wspec, sector_kernels=sector_kernels)
        self._tops[wl] = t
        return t

    def _loop_kernel(self, vin: "_TableView", c: int) -> np.ndarray:
        """(T, J, M[, 4, 4]): the loop kernel K[t, j, a] of the inside table's R cells in azimuthal modes, times
        the receiving cell's projected solid angle.  A wavelength's tables' part (`_table_ops`) lets it go
        once its operators are made (`_operators`: the kernel then lives in the round-trip system and its
        factors); a solver of another bulk on the same tables makes it again, the same numbers."""
        Kh = np.moveaxis(vin.diffuse_modes("R", self.theta_c, self.theta_c, self.delta), 0, 1)
        Kh *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
        return Kh

    def _operators(self, wl: float) -> dict:
        if wl in self._ops:
            return self._ops[wl]
        m = self.model
        t = self._table_ops(wl)
        c, RF, SR, Kh, KBh = t["c"], t["RF"], t["SR"], t["Kh"], t["KBh"]
        current_memory().reserve(_system_bytes(self.theta_c.size * c, self.delta.size // 2 + 1))
        if Kh is None:                        # let go by an earlier solver on these tables (`_loop_kernel`)
            Kh = self._loop_kernel(t["vin"], c)
        t["Kh"] = None                        # from here on it lives in this wavelength's system
        tc = self.theta_c
        N = tc.size
        cos_c = np.maximum(np.cos(np.radians(tc)), 1e-6)
        absorb = np.exp(-m.absorption_per_m * m.thickness_m / cos_c)                       # (N,)
        Mk = Kh.shape[2]
        # round trip diagonal D_j = A_j R_F,j A_j (4x4 or scalar R_F,00)
        if c == 1:
            Dj = absorb**2 * RF[:, 0, 0]
            Kmat = np.moveaxis(Kh, 2, 0) + np.diag(SR[:, 0, 0])[None]                      # (M, T, J)
            sysm = np.eye(N)[None] - Kmat * Dj[None, None, :]
        else:
            Dj = absorb[:, None, None] ** 2 * RF                                            # (N, 4, 4)
            KD = np.empty((Mk, N, 4, N, 4), np.result_type(Kh, Dj))                       # C order: the reshape
            # KD[m, t, a, j, c] = sum_b Kh[t, j, m, a, b] Dj[j, b, c]: a batched 4x4 product written in the
            # system's layout (np.matmul over (1 x 4) @ (4 x 4): 7x faster than the einsum on 90 x 90 x 37)
            np.matmul(np.transpose(Kh, (2, 0, 3, 1, 4))[..., None, :], Dj, out=KD[..., None, :])  # reshape: a view
            idx = np.arange(N)
            KD[:, idx, :, idx, :] += np.einsum("jab,jbc->jac", SR, Dj)[:, None]
            sysm = KD.reshape(Mk, N * 4, N * 4)
            sysm *= -1.0                                                                    # I - K D in place
            sysm[:, np.arange(N * 4), np.arange(N * 4)] += 1.0
            del KD
        Kb = Rtrip = KBm = None
        if t["vB"] is not None:
            # second face with its own table: round trip K A (K_B + R_B,delta) A as full matrices per m
            Kb = _blocks(Kh, c) + _block_diag(SR, c)[None]
            Aa = np.repeat(absorb, c)
            KBm = _blocks(KBh, c)
            Rtrip = (KBm + _block_diag(RF, c)[None]) * Aa[None, :, None] * Aa[None, None, :]
            sysm = np.eye(N * c)[None] - Kb @ Rtrip
        slab_ops = None
        if m.scatter_per_m > 0:   # volume scattering: the slab's operators replace the diagonal traversal
            Kb = _blocks(Kh, c) + _block_diag(SR, c)[None]
            R2 = (0.0 if KBm is None else KBm) + _block_diag(RF, c)[None]
            slab_ops = _slab_system(m, self.theta_edges, self.delta.size, Kb, R2, c)
            Rtrip, sysm = slab_ops["Rtrip"], slab_ops["sys"]
        ops = dict(wl=wl, n=t["n"], n0=t["n0"], vin=t["vin"], vB=t["vB"], absorb=absorb, RF=RF, sys=sysm, Dj=Dj,
                   GhT=t["GhT"], sectors=t["sector_kernels"] if slab_ops is None else None,
                   Wflat=t["Wflat"], Wspec=t["Wspec"], c=c, M=Mk, Kb=Kb, Rtrip=Rtrip, GBT=t["GBT"], slab=slab_ops)
        ops.update(self._outside_ops(wl, ops))
        self._ops[wl] = ops
        return ops

    def _outside_ops(self, wl: float, ops: dict) -> dict:
        """The outside table's part of a wavelength's operators: its view, and whether the direct
        reflection and the first transmitted pass are read from its own finer grid
        (plate.detector.direct_reading) while the loop works on the engine grid."""
        vout = _TableView(self.outside, wl, self.mueller, "outside table") if self.outside is not None else None
        out_on_grid = vout is None or vout.on_grid(self.theta_edges, self.delta.size)
        direct = (not out_on_grid and self.model.rough_face == "front" and ops["vB"] is None and ops["slab"] is None)
        return dict(vout=vout, out_on_grid=out_on_grid, direct=direct, solved={})   # `solve`'s results: anew

    def with_outside(self, model: EngineSetup, outside: BsdfTable) -> "PlateSolver":
        """This solver for another outside table (and instrument) on the same inside, back and sector
        tables and plate: the loop's operators (kernels, round trip, exit maps) depend on those alone,
        so only the outside table's part is re-derived (a tilt or a beam traced into the outside
        table changes that table alone).  The numbers are those of a fresh solver."""
        new = copy.copy(self)
        new.model, new.outside, new._twins = model, outside, {}
        new._ops = {wl: {**ops, **new._outside_ops(wl, ops)} for wl, ops in self._ops.items()}
        return new

    def _exit_maps(self, vin: "_TableView", vB: "_TableView | None", n: float, n0: float,
                   c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(GhT, Wflat, Wspec): how diffuse internal light leaves through each face onto the outgoing grid.

        GhT: the rough face's inside T cells per azimuthal mode.  Wflat / Wspec: exit through the
        second face's Fresnel (or its table's delta part) and through the rough face's delta part: a
        conservative Snell remap (each outgoing cell cut into 64 equal projected-solid-angle slices,
        each slice's pre-image in one internal cell, exact transmission per slice, Mueller row 0).
        """
        tc, N, e = self.theta_c, self.theta_c.size, np.radians(self.theta_edges)
        GhT = self._exit_kernel(vin, c)
        ns = 64
        u = (np.sin(e[:-1])[:, None] ** 2 + (np.arange(ns) + 0.5)[None] / ns
             * (np.sin(e[1:]) ** 2 - np.sin(e[:-1]) ** 2)[:, None])                           # (O, ns)
        th_int = _snell_deg(np.degrees(np.arcsin(np.sqrt(u))), n0, n)
        if vB is None:
            tf = _fresnel(np.cos(np.radians(th_int)), n, n0, "T")[..., 0, :c] / ns           # (O, ns, c)
        else:
            tf = vB.specular_many("T", th_int).reshape(N, ns, 4, 4)[..., 0, :c] / ns
        # internal radiance linearly interpolated between cell centres, held constant across the
        # critical angle (trapped cells never feed the exit) and at the grid ends
        below = tc < np.degrees(np.arcsin(min(n0 / n, 1.0)))
        Wi = _lin_matrix(tc[below], th_int.ravel()).reshape(N, ns, -1)                       # (O, ns, Nb)

        def exit_remap(t_slices: np.ndarray) -> np.ndarray:
            """(O, N, c): internal radiance -> outgoing cells, through transmission t per slice."""
            W = np.zeros((N, N, c))
            W[:, below, :] = np.einsum("osj,osc->ojc", Wi, t_slices)
            return W
        Wspec = exit_remap(vin.specular_many("T", th_int).reshape(N, ns, 4, 4)[..., 0, :c] / ns)
        return GhT, exit_remap(tf), Wspec

    def _exit_kernel(self, vin: "_TableView", c: int) -> np.ndarray:
        """(M, J c, O): a table's inside T cells (diffuse light leaving through the rough face from inside)
        per azimuthal mode, detector row S0 of the Mueller matrix."""
        tc = self.theta_c
        Gh = vin.diffuse_modes("T", tc, tc, self.delta, detector_row=True)                 # (J, O, M[,4])
        return (np.moveaxis(Gh, 2, 0) if c == 1 else np.moveaxis(Gh, (2, 3), (0, 2))).reshape(Gh.shape[2], -1,
                                                                                              Gh.shape[1])

    def solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float = 0.0) -> list[PlateResult]:
        """Plate BSDF for each incidence angle (degrees) at one wavelength.

        Of the instrument only the source's polarisation enters the solve (the incidences are given),
        and every part of the field is linear in the source's Stokes vector s (Mueller tables, Fresnel
        matrices, the loop's linear systems): the field of s is sum_k s_k F(e_k), F(e_k) the field of
        the k-th unit Stokes vector, solved once each.  (With depolarising tables the diffuse parts take
        the source's intensity alone while the flat faces' delta beams see its polarisation: not linear
        in s, so that field is solved, and kept, for s itself.)  The fields are kept with the
        wavelength's operators (`_SOLVED_KEPT` requests, `_SOLVED_BYTES` at most), which the solvers
        that differ only in the instrument share (`_reused_solver`): an evaluation that changes only
        the source's polarisation or how the rows are read (stray light; a cone or blur too where the
        tables' direct grid does not adapt to it) solves nothing.  An unpolarised source's field is
        F(e_0) itself, bit for bit; the sector loop's GMRES (relative tolerance 1e-7) solves each unit
        source to its tolerance.  Results are never changed by their readers (`dataclasses.replace`)."""
        twin = self._twin_wavelength(float(wavelength_nm))
        if twin != float(wavelength_nm):
            return [replace(r, wavelength_nm=float(wavelength_nm)) for r in self.solve(twin, theta_i_deg, phi_i_deg)]
        ops = self._operators(float(wavelength_nm))
        s = np.asarray(self.model.source_stokes, float)
        if not self.mueller or (s[0] == 1.0 and not s[1:].any()):
            return list(self._field(ops, wavelength_nm, theta_i_deg, phi_i_deg, s))
        parts = [(np.eye(4)[k], float(s[k])) for k in range(4) if s[k] != 0.0]
        fields = [self._field(ops, wavelength_nm, theta_i_deg, phi_i_deg, e) for e, _ in parts]
        return [_stokes_sum([f[q] for f in fields], [w for _, w in parts]) for q in range(len(fields[0]))]

    def _twin_wavelength(self, wl: float) -> float:
        """The wavelength solved in place of `wl`: the shortest of the tables' wavelengths whose every input
        is that of `wl` (the indices inside and outside, every table's row: a geometric-optics relief at a
        recording's wavelengths without dispersion, `plate.faces.same_indices`), else `wl` itself.  Its
        results are those of `wl` (the plate's bulk and instrument do not depend on the wavelength), so a
        recording at three wavelengths without dispersion is solved once."""
        tables = [t for t in (self.inside, self.outside, self.back, self.inside_sectors) if t is not None]
        m = self.model
        n = (complex(m.index.n(wl)), complex(m.outside_index.n(wl)))
        key = (wl, n) + tuple(id(t) for t in tables)          # the tables are the solver's (held while it lives)
        if key not in self._twins:
            same = (float(w) for w in np.sort(np.asarray(self.inside.wavelength_nm, float)) if w < wl
                    and (complex(m.index.n(w)), complex(m.outside_index.n(w))) == n
                    and all(t.same_at(float(w), wl) for t in tables))
            self._twins[key] = next(same, wl)                   # the shortest twin (compared lazily), else wl
        return self._twins[key]

    def _field(self, ops: dict, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float,
               stokes: np.ndarray) -> list[PlateResult]:
        """The plate's results for the source Stokes vector `stokes` (kept with the operators: `solve`)."""
        key = (np.asarray(theta_i_deg, float).tobytes(), float(phi_i_deg), np.asarray(stokes, float).tobytes())
        kept = ops["solved"]
        if key not in kept:
            with blas_single_thread():
                res = self._solve(wavelength_nm, theta_i_deg, phi_i_deg, stokes)
            size = sum(_result_bytes(r) for r in res)
            if size > _SOLVED_BYTES:
                return res
            kept[key] = (res, size)
            while len(kept) > _SOLVED_KEPT or sum(z for _, z in kept.values()) > _SOLVED_BYTES:
                kept.pop(next(iter(kept)))
        return kept[key][0]

    def _solve(self, wavelength_nm: float, theta_i_deg: Sequence[float], phi_i_deg: float,
               stokes: np.ndarray) -> list[PlateResult]:
        ops = self._operators(float(wavelength_nm))
        thetas = np.atleast_1d(np.asarray(theta_i_deg, float))
        src = _Sources.empty(thetas.size, self.theta_c.size, self.delta.size, ops["c"])
        for q, ti in enumerate(thetas):
            self._incidence(ops, src, q, abs(float(ti)), stokes)
        out_rough, out_flat = self._diffuse_exits(ops, src, thetas)
        front = self.model.rough_face == "front"
        first_T = self._flat_exit(ops, src.S_first) if ops["direct"] else None
        results = []
        for q, ti in enumerate(thetas):
            gR = src.direct_R[q] + (out_rough[q] if front else out_flat[q])
            gT = out_flat[q] if front else out_rough[q]
            r = PlateResult(float(wavelength_nm), float(ti), float(phi_i_deg), self.theta_c,
                            self.theta_edges, self.delta, gR, gT, src.deltas[q])
            if src.direct[q] is not None:   # the loop on the engine grid, the direct parts on their own grid
                r = replace(r, direct=src.direct[q], loop_R=out_rough[q], loop_T=out_flat[q] - first_T[q])
            results.append(r)
        return results

    def _flat_exit(self, ops: dict, S: np.ndarray) -> np.ndarray:
        """(q, O, A) BSDF through the flat second face of power per cell S (q, N, A, c) arriving there
        after one traversal (absorption), by the same Snell remap as the loop's exit (`_exit_maps`)."""
        c, n, n0, psa = ops["c"], ops["n"], ops["n0"], self.psa
        nI, N, A = S.shape[0], self.theta_c.size, self.delta.size
        L = np.moveaxis(S * ops["absorb"][None, :, None, None] / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)
        return (ops["Wflat"].reshape(N, N * c) @ L) * (n0 / n) ** 2

    def _direct_field(self, ops: dict, ti: float, s_inc: np.ndarray) -> "DirectField":
        """The outside table's cells at incidence ti as the detector reads them (plate.detector.DirectField):
        R, the direct reflection's S0; T, the Stokes vector of the first transmission inside the glass,
        leaving through the flat face with Fresnel T, (n0/n)^2 (radiance law) and Beer-Lambert absorption."""
        vout, c, m = ops["vout"], ops["c"], self.model
        f_r, f_t = vout.at_incidence("R", ti), vout.at_incidence("T", ti)
        R = f_r if c == 1 else f_r[..., 0, :] @ s_inc
        T = f_t[..., None] if c == 1 else f_t @ s_inc
        n, n0 = ops["n"], ops["n0"]

        def t_exit(theta_int_deg: np.ndarray) -> np.ndarray:
            cos_t = np.cos(np.radians(theta_int_deg))
            tf = _fresnel(cos_t, n, n0, "T")[..., 0, :c]
            return tf * ((n0 / n) ** 2 * np.exp(-m.absorption_per_m * m.thickness_m / np.maximum(cos_t, 1e-6)))[:, None]
        t = vout.table
        return DirectField(np.asarray(t.theta_s_edges_deg, float),
                           np.asarray(t.phi_s_edges_deg, float) - (vout.phi0 + 180.0),
                           np.asarray(R, float), np.asarray(T, float), n0 / n, t_exit)

    def _incidence(self, ops: dict, src: "_Sources", q: int, ti: float, s_inc: np.ndarray) -> None:
        """Incidence q: first-face scattering of the source (Stokes vector s_inc), the delta-beam chain,
        and what the beams scatter."""
        m, c, vin, vout, vB = self.model, ops["c"], ops["vin"], ops["vout"], ops["vB"]
        n, n0, tc, psa, delta = ops["n"], ops["n0"], self.theta_c, self.psa, self.delta
        tt = float(_snell_deg(ti, n0, n))
        a_t = float(np.exp(-_beam_extinction(m, ops["slab"], self.theta_edges, tt) * m.thickness_m
                           / max(np.cos(np.radians(tt)), 1e-6)))
        if vB is None:
            RFt, TFt = _fresnel(np.cos(np.radians(tt)), n, n0, "R"), _fresnel(np.cos(np.radians(tt)), n, n0, "T")
        else:
            RFt, TFt = vB.specular("R", tt), vB.specular("T", tt)
        deltas = []
        if m.rough_face == "front":
            if not ops["out_on_grid"]:
                f_r = vout.cells("R", ti, self.theta_edges, delta)
                f_t = vout.cells("T", ti, self.theta_edges, delta)
                if ops["direct"]:
                    src.direct[q] = self._direct_field(ops, ti, s_inc)
                    # the first pass is read on the direct grid; in the loop the first transmission is
                    # only the source of the later passes: its azimuth cells enter as point sources at
                    # their centres, weighted by the centre values (no binning variance, module doc)
                    f_t = centre_values(f_t, clip=False)
            else:
                f_r = vout.diffuse("R", [ti], tc, delta)[0]
                f_t = vout.diffuse("T", [ti], tc, delta)[0]
            src.direct_R[q] = f_r if c == 1 else f_r[..., 0, :] @ s_inc
            src.S[q] = (f_t * psa[:, None])[..., None] if c == 1 else (f_t @ s_inc) * psa[:, None, None]
            src.S_first[q] = src.S[q]
            y0, z0 = vout.specular("T", ti) @ s_inc, np.zeros(4)
            deltas.append(("R", ti, 0.0, float((vout.specular("R", ti) @ s_inc)[0])))
        else:
            cos_i = np.cos(np.radians(ti))
            deltas.append(("R", ti, 0.0, float((_fresnel(cos_i, n0, n, "R") @ s_inc)[0])))
            y0, z0 = np.zeros(4), a_t * (_fresnel(cos_i, n0, n, "T") @ s_inc)
        # delta chain: z arrives at the rough face from inside, y leaves it into the plate
        sR, sT = vin.specular("R", tt), vin.specular("T", tt)
        loop = a_t * a_t * RFt
        z = np.linalg.solve(np.eye(4) - loop @ sR, z0 + loop @ y0)
        y = y0 + sR @ z
        front = m.rough_face == "front"
        deltas.append(("R" if front else "T", ti, 0.0, float((sT @ z)[0])))
        deltas.append(("T" if front else "R", ti, 0.0, float((TFt @ (a_t * y))[0])))
        src.deltas.append(deltas)
        src.beams[q] = y, (z / a_t if a_t > 1e-300 else 0.0 * z)
        self._beam_scattering(ops, src, q, tt, a_t * y, z)

    def _beam_scattering(self, ops: dict, src: "_Sources", q: int, tt: float, yb: np.ndarray, z: np.ndarray) -> None:
        """Diffuse light the delta beams make at the faces: yb at a back-face table, z at the rough face."""
        c, vin, vB, tc, psa, delta = ops["c"], ops["vin"], ops["vB"], self.theta_c, self.psa, self.delta
        if vB is not None:
            up_absorb = ops["absorb"] if ops["slab"] is None else 1.0     # a slab's operators carry the traversal
            fbr = vB.diffuse("R", [tt], tc, delta)[0]
            fbt = vB.diffuse("T", [tt], tc, delta)[0]
            if c == 1:
                src.U_extra[q, :, :, 0] = fbr * (psa * up_absorb)[:, None] * yb[0]
                src.direct_flat[q] = fbt * yb[0]
            else:
                src.U_extra[q] = (fbr @ yb) * (psa * up_absorb)[:, None, None]
                src.direct_flat[q] = fbt[..., 0, :] @ yb
        fr = vin.diffuse("R", [tt], tc, delta)[0]
        ft = vin.diffuse("T", [tt], tc, delta)[0]
        if c == 1:
            src.S[q, :, :, 0] += fr * psa[:, None] * z[0]
            src.direct_rough[q] += ft * z[0]
        else:
            src.S[q] += (fr @ z) * psa[:, None, None]
            src.direct_rough[q] += ft[..., 0, :] @ z

    def _diffuse_loop(self, ops: dict, src: "_Sources", thetas: np.ndarray) -> dict:
        """Solve X = S + Kb Rc X per azimuthal mode; return the light at both faces (modes and cells)."""
        c, Mk, vB, slab = ops["c"], ops["M"], ops["vB"], ops["slab"]
        nI, N, A = thetas.size, self.theta_c.size, self.delta.size
        to_modes = lambda arr: np.moveaxis(np.moveaxis(np.fft.rfft(arr, axis=2), 2, 1).reshape(nI, Mk, N * c), 0, 2)  # noqa: E731
        to_cells = lambda YM: np.fft.irfft(np.moveaxis(np.moveaxis(YM, 2, 0).reshape(nI, Mk, N, c), 1, 2), n=A, axis=2)  # noqa: E731
        rhs = to_modes(src.S)                                                # (M, N c, nI)
        Uxh = Dxh = None
        if vB is not None or slab is not None:
            Uxh = to_modes(src.U_extra)
            if slab is not None:   # with the slab: U_extra leaves the back face upward; beams shed light
                Uxh, Dxh = _slab_sources(slab, Uxh, src.beams, self.theta_edges, thetas, ops["n0"], ops["n"], c)
            rhs = rhs + ops["Kb"] @ Uxh
        if ops["sectors"] is not None:   # an anisotropic relief: the loop meets the relief by azimuth sector
            XhM = self._sector_loop(ops, rhs, to_modes, to_cells)
        else:
            XhM = _loop_solve(ops, rhs)                                      # (M, N c, nI)
        absorb = ops["absorb"]
        out = {"XhM": XhM, "Uxh": Uxh}
        if slab is not None:       # light arriving at the second face: B X + what the beams shed there
            out["DbM"] = slab["B"] @ XhM + Dxh
            out["at_flat"] = to_cells(out["DbM"])
        else:
            out["at_flat"] = to_cells(XhM) * absorb[None, :, None, None]
        if vB is None and slab is None:    # back up to the rough face through the flat face's Fresnel R
            U = _reflect_up(ops, out["at_flat"])
            out["Um"] = _exit_modes(U)                                                          # (M, q, J c)
            out["U"] = U
        else:
            out["Um"] = np.moveaxis(ops["Rtrip"] @ XhM + Uxh, 2, 1)                         # (M, q, J c)
            out["U"] = None
        return out

    def _diffuse_exits(self, ops: dict, src: "_Sources", thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(out_rough, out_flat): the plate's diffuse BSDF leaving through each face, (q, O, A)."""
        c, Mk, n, n0 = ops["c"], ops["M"], ops["n"], ops["n0"]
        nI, N, A, psa = thetas.size, self.theta_c.size, self.delta.size, self.psa
        d = self._diffuse_loop(ops, src, thetas)
        Um = d["Um"]
        # rough-face exit: circular convolution over azimuth with the inside T kernel
        out_rough = _rough_exit(Um, ops["GhT"], A) + src.direct_rough
        if ops["sectors"] is not None:   # an anisotropic relief: every order leaves by azimuth sector
            out_rough = out_rough + self._sector_exits(ops, d["U"], A)
        if np.any(ops["Wspec"]):   # specular exit of the diffuse light arriving at the rough face from inside
            U = d["U"] if d["U"] is not None else np.fft.irfft(np.moveaxis(Um.reshape(Mk, nI, N, c), 0, 2), n=A, axis=2)
            LU = np.moveaxis(U / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)
            out_rough = out_rough + (ops["Wspec"].reshape(N, N * c) @ LU) * (n0 / n) ** 2
        # flat-face exit: internal radiance (Stokes) interpolated at the Snell pre-image of each outgoing
        # direction, times the exact Fresnel transmission there, divided by (n/n0)^2 (radiance law)
        L = np.moveaxis(d["at_flat"] / psa[None, :, None, None], 2, 3).reshape(nI, N * c, A)  # (q, N c, A)
        out_flat = (ops["Wflat"].reshape(N, N * c) @ L) * (n0 / n) ** 2                     # (q, O, A)
        if ops["vB"] is not None:   # diffuse exit through the back-face table, from the light arriving there
            AX = d["DbM"] if ops["slab"] is not None else d["XhM"] * np.repeat(ops["absorb"], c)[None, :, None]
            out_flat = (out_flat + np.fft.irfft(np.moveaxis(np.moveaxis(AX, 2, 1) @ ops["GBT"], 0, 2), n=A, axis=2)
                        + src.direct_flat)
        return out_rough, out_flat


@dataclass
class _Sources:
    """Per-incidence source terms of the round-trip problem (power per cell / BSDF on the grid)."""

    S: np.ndarray               # (q, N, A, c) leaving the rough face into the plate
    direct_rough: np.ndarray    # (q, N, A) BSDF through the rough face without the loop
    direct_R: np.ndarray        # (q, N, A) outside table R (front relief)
    direct_flat: np.ndarray     # (q, N, A) diffuse exit of the delta beam through a back-face table
    U_extra: np.ndarray         # (q, N, A, c) delta beam scattered diffusely by a back-face table
    beams: np.ndarray           # (q, 2, 4) down beam y at the first face, up beam at the second face
    S_first: np.ndarray         # (q, N, A, c) the part of S that is the outside table's first transmission
    deltas: list = field(default_factory=list)
    direct: list = field(default_factory=list)   # per incidence: DirectField or None

    @staticmethod
    def empty(nI: int, N: int, A: int, c: int) -> "_Sources":
        z = np.zeros
        return _Sources(z((nI, N, A, c)), z((nI, N, A)), z((nI, N, A)), z((nI, N, A)), z((nI, N, A, c)),
                        z((nI, 2, 4)), z((nI, N, A, c)), direct=[None] * nI)


def _stokes_sum(results: list, weights: list) -> PlateResult:
    """sum_k w_k results_k of one incidence's PlateResults for unit sources (`PlateSolver.solve`): every
    field linear in the source, the delta beams' powers too (same directions in each)."""
    first = results[0]

    def add(get):
        parts = [get(r) for r in results]
        return None if parts[0] is None else sum(w * p for w, p in zip(weights, parts))
    deltas = [(sd, t, d, float(sum(w * r.deltas[i][3] for w, r in zip(weights, results))))
              for i, (sd, t, d, _) in enumerate(first.deltas)]
    direct = first.direct
    if direct is not None:
        direct = replace(direct, R=add(lambda r: r.direct.R), T=add(lambda r: r.direct.T))
    return replace(first, grid_R=add(lambda r: r.grid_R), grid_T=add(lambda r: r.grid_T), deltas=deltas,
                   direct=direct, loop_R=add(lambda r: r.loop_R), loop_T=add(lambda r: r.loop_T))


def _system_bytes(nc: int, modes: int) -> int:
    """What making a wavelength's operators allocates beside what is held (`PlateSolver._operators`): the
    (M, N c, N c) complex round-trip system and as much again while it is built and factorised (its
    product's scratch, the LU factors made from it)."""
    return 2 * modes * nc * nc * 16


def _sector_bytes(sectors: Any, N: int, c: int, modes: int, incidences: int) -> int:
    """What making a wavelength's sector kernels allocates (`SectorLoop._sector_kernels`): the stacked
    single-precision loop differences on the tables' incidences, their exits, and one sector's
    double-precision kernel being made."""
    k, nc, ic = np.asarray(getattr(sectors, "phi_i_deg", [0.0])).size, N * c, min(incidences, N) * c
    return modes * nc * (2 * k * ic * 4 + k * N * 8 + nc * 16)


def _result_bytes(r: PlateResult) -> int:
    """Bytes of a PlateResult's fields (the kept fields' budget, `_SOLVED_BYTES`)."""
    arrays = [r.grid_R, r.grid_T, r.loop_R, r.loop_T]
    if r.direct is not None:
        arrays += [r.direct.R, r.direct.T, *r.direct._slopes["R"], *r.direct._slopes["T"]]
    return int(sum(a.nbytes for a in arrays if isinstance(a, np.ndarray)))


_SOLVED_KEPT = 8             # unit-source fields kept per wavelength's operators (`PlateSolver.solve`) ...


_SOLVED_BYTES = 150e6        # ... and their bytes at most (a beam divergence's many incidences: not kept)
