"""The plate's loop by azimuth sector (an anisotropic relief's inside sector tables, `plate.faces.inside_sectors`):
the kernels' differences from the 0-deg table (`_SectorKernels`, single precision: the argument is its
docstring), the loop solved by GMRES preconditioned by the circulant loop, the exits by sector, and what
a solver keeps of the sector table once its kernels exist (`SectorsHeader`)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from relief_bsdf.bsdf.table import ROW_ARRAYS, BsdfTable
from relief_bsdf.plate.modes import _blocks, _exit_modes, _lu_apply, _lu_factors, _rough_exit
from relief_bsdf.plate.tableview import _lin_matrix, _TableView


def _phi_slice(table: BsdfTable, ip: int) -> BsdfTable:
    """The table at its ip-th incidence azimuth only (every array's phi_i axis, axis 2, cut to one)."""
    kw = {"phi_i_deg": np.asarray(table.phi_i_deg)[ip:ip + 1]}
    for name in ROW_ARRAYS:
        a = getattr(table, name)
        if a is not None:
            kw[name] = a[:, :, ip:ip + 1]
    return replace(table, **kw)


class SectorLoop:
    """PlateSolver's loop and exits by azimuth sector (an anisotropic relief's inside sector tables)."""

    def _sector_kernels(self, wl: float, c: int, moving: tuple[float, float] | None, vin: _TableView,
                        Kh: np.ndarray, GhT: np.ndarray) -> "_SectorKernels":
        """The inside sector tables' (`inside_sectors`) loop and exit kernels minus the 0-deg table's (`vin`:
        its loop kernel Kh, exit kernel GhT), in the engine's modes like the 0-deg table's (`moving`: as the
        0-deg table's view, `_table_ops`).  Each loop difference is written straight into its slice of the
        stacked single precision array (`_SectorKernels.loop`): no (M, N c, N c) complex copy per sector.

        The loop kernel of a table is its reflected cells on the engine's exit cells (the inside tables are
        made on the engine grid), in azimuthal modes, LINEAR in the table's incidences theta_i: K = R W^T,
        R on the table's I incidences, W (N, I) the linear interpolation onto the engine's N cells
        (`_TableView.diffuse_modes`; the reflected side blends, only the transmitted side's lobes move).
        Where the sector tables have the 0-deg table's incidences, the differences are kept as
        dR = R_k - R_0 on those I incidences (I ~ N / 2: half the bytes and half the product of every
        GMRES iteration) and W applied to the light (`_SectorKernels.interp`); else on the engine's cells."""
        t = self.inside_sectors
        if isinstance(t, SectorsHeader):
            raise RuntimeError(f"the inside sector table was dropped before the kernels at {wl:g} nm were made")
        ps = np.asarray(t.phi_i_deg, float)
        th_i = np.asarray(vin.table.theta_i_deg, float)
        factored = SECTOR_LOOP_ON_TABLE_INCIDENCES and np.array_equal(np.asarray(t.theta_i_deg, float), th_i)
        base = self._reflected_modes(vin, c) if factored else Kh
        M, nc = Kh.shape[2], Kh.shape[0] * c
        ic = base.shape[1] * c
        loop = np.empty((M, 2 * nc, ps.size * ic), SECTOR_LOOP_DTYPE)
        exits = []
        for ip, p in enumerate(ps):
            v = _TableView(_phi_slice(t, ip), wl, self.mueller, "inside sector table", moving)
            if factored:
                K = self._reflected_modes(v, c)
            else:
                K = np.moveaxis(v.diffuse_modes("R", self.theta_c, self.theta_c, self.delta), 0, 1)
                K *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
            K -= base
            _blocks(K.real, c, out=loop[:, :nc, ip * ic:(ip + 1) * ic])
            _blocks(K.imag, c, out=loop[:, nc:, ip * ic:(ip + 1) * ic])
            del K
            exits.append((self._exit_kernel(v, c) - GhT).astype(SECTOR_EXIT_DTYPE))
        interp = _lin_matrix(th_i, self.theta_c) if factored else None
        return _SectorKernels(ps, loop, tuple(exits), interp)

    def _reflected_modes(self, v: _TableView, c: int) -> np.ndarray:
        """(T, I, M[, 4, 4]): a table's reflected cells on the engine's exit cells at the table's OWN
        incidences, in azimuthal modes, times the receiving cell's projected solid angle (the loop kernel
        before the interpolation in theta_i, `_sector_kernels`)."""
        arr = v._on_exit_grid("R", self.theta_c, self.delta)
        K = np.moveaxis(np.fft.rfft(arr, axis=2), 0, 1)
        K *= self.psa[:, None, None] if c == 1 else self.psa[:, None, None, None, None]
        return K

    def _sector_cells(self, sk: "_SectorKernels") -> np.ndarray:
        """(K, A) 0/1: the propagation azimuths delta that meet the relief through sector k.  The inside
        table traced at incidence azimuth p stands for light arriving at propagation azimuth p + 180
        (methods.ray's frame), i.e. at delta = p for rows lit at phi_i = 0 (the engine's frame for an
        anisotropic relief); each cell takes the nearest p mod 180 (a half turn leaves a relief's
        statistics unchanged; without a sector at 0 deg the 0-deg inside table's cells are those of no
        sector), whose table averages the sector's incidence azimuths (`plate.faces.inside_sectors`;
        measured on the anisotropic relief of bench_forward_accuracy with tables at the sectors' centres:
        rms z 1.45 with 30-deg sectors, 1.12 with 15; blending the two nearest tables instead of taking
        the nearest: 1.37 / 1.15, but the measured map 1.70 -> 1.75 / 1.77)."""
        own = np.asarray(sk.azimuths_deg, float)
        first = 0 if own.size and own[0] == 0.0 else 1          # the 0-deg table among the sectors, or the base
        ps = own if first == 0 else np.concatenate([[0.0], own])
        d = np.abs(np.mod(self.delta[:, None] - ps[None, :] + 90.0, 180.0) - 90.0)       # (A, 1 + K)
        near = np.argmin(d, axis=1)
        return (near[None, :] == np.arange(first, ps.size)[:, None]).astype(float)

    def _sector_masks(self, ops: dict) -> np.ndarray:
        """(K, A) the sectors' cells (`_sector_cells`, the loop's and the exits'); the tables and the grid fix
        them, so they are computed once per wavelength and shared by the solvers whose bulk differs
        (`_table_ops`)."""
        t = self._tops[ops["wl"]]
        if "sector_cells" not in t:
            t["sector_cells"] = self._sector_cells(ops["sectors"])
        return t["sector_cells"]

    def _sector_average(self, ops: dict) -> tuple[np.ndarray, np.ndarray]:
        """((K, A) sector cells, sum_k w_k dK_k): the sectors' cells (`_sector_masks`) and the azimuth-weighted
        kernel difference of the sector loop's preconditioner (`_sector_loop`), made when a bulk's system
        is factorised and not kept (one pass over the kernels; (M, N c, N c) it would hold as much as the
        factors)."""
        P = self._sector_masks(ops)
        return P, ops["sectors"].weighted(P.mean(axis=1))

    def _sector_loop(self, ops: dict, S: np.ndarray, to_modes: Any, to_cells: Any) -> np.ndarray:
        """X (M, N c, q) in modes solving X = S + K D X with the rough face's loop kernel K taken by azimuth
        sector (an anisotropic relief, `inside_sectors`): light arriving at the relief from inside at
        propagation azimuth delta scatters by the table traced nearest delta (`_sector_cells`), so K is
        K_0 + sum_k dK_k P_k (P_k: the cells of sector k) and no longer circulant.  Every order of the
        loop meets the relief by its own azimuth: the second pass (the light transmitted by the relief and
        reflected by the flat face) and the trapped light.

        Solved by GMRES, preconditioned by the circulant loop of the sectors' azimuth-weighted kernel
        Kw = K_0 + sum_k w_k dK_k (w_k: sector k's share of the azimuth cells; exact when the light is
        uniform in azimuth): (I - (I - Kw D)^-1 sum_k dK_k (P_k - w_k) D) X = (I - Kw D)^-1 S, all
        incidences in one Krylov space (the operator is the same for each); the sum over the sectors is
        one single-precision product (`_SectorKernels.apply`)."""
        from scipy.sparse.linalg import LinearOperator, gmres
        c, Dj, sk = ops["c"], ops["Dj"], ops["sectors"]
        if "sector_loop" not in ops:
            P, avg = self._sector_average(ops)
            if c == 1:                                                                 # avg D, D diagonal
                avgD = avg * Dj[None, None, :]
            else:                                                                      # D block-diagonal
                M, nc = avg.shape[:2]
                avgD = (avg.reshape(M, nc, nc // 4, 1, 4) @ Dj[None, None]).reshape(avg.shape)
            ops["sector_loop"] = (_lu_factors(ops.pop("sys") - avgD),     # the factors replace the system
                                  P - P.mean(axis=1)[:, None])
        pre, Pw = ops["sector_loop"]
        shape = to_cells(S).shape                                                          # (q, N, A, c)

        def round_trip(X: np.ndarray) -> np.ndarray:       # D X: absorb, flat face's Fresnel R, absorb
            if c == 1:
                return X * Dj[None, :, None, None]
            return np.einsum("jab,qjkb->qjka", Dj, X)

        def extra(X: np.ndarray) -> np.ndarray:            # (I - Kw D)^-1 sum_k dK_k (P_k - w_k) D X, cells
            Y = round_trip(X)
            Z = sk.apply(np.stack([to_modes(Y * m[None, None, :, None]) for m in Pw]))
            return to_cells(_lu_apply(pre, Z))

        b = to_cells(_lu_apply(pre, S)).ravel()
        op = LinearOperator((b.size, b.size), matvec=lambda x: x - extra(x.reshape(shape)).ravel(), dtype=float)
        x, info = gmres(op, b, x0=b.copy(), rtol=1e-7, atol=0.0, restart=40, maxiter=20)
        if info != 0:
            raise RuntimeError(f"plate loop by azimuth sector: GMRES did not converge ({info} iterations)")
        return to_modes(x.reshape(shape))

    def _sector_exits(self, ops: dict, U: np.ndarray, A: int) -> np.ndarray:
        """(q, O, A): what the exit through the rough face changes when the light arriving there from inside
        (U, cells, every order) leaves by azimuth sector, each through its own inside table instead of the
        0-deg one turned (added to the rough face's diffuse exit; the exit is linear in the kernel)."""
        out = 0.0
        for dG, mask in zip(ops["sectors"].exits, self._sector_masks(ops)):
            if mask.any():
                out = out + _rough_exit(_exit_modes(U * mask[None, None, :, None]), dG, A)
        return out


SECTOR_LOOP_DTYPE = np.float32      # the sector loop's kernel differences (`_SectorKernels`: precision argument)


SECTOR_EXIT_DTYPE = np.complex64    # the sector exits' kernel differences


SECTOR_LOOP_ON_TABLE_INCIDENCES = True   # the loop differences kept on the tables' incidences (`_sector_kernels`)


@dataclass(frozen=True)
class _SectorKernels:
    """The inside sector tables' kernels minus the 0-deg table's (`PlateSolver._sector_kernels`).

    `loop` (M, 2 N c, K I c) SECTOR_LOOP_DTYPE: per azimuthal mode the K loop-kernel differences dR_k side by
    side, their real parts over their imaginary parts, so that sum_k dK_k Y_k is ONE real product per mode
    (`apply`): the loop's GMRES applies it at every iteration, and at a few right-hand sides a complex
    product per sector is bound by reading the kernels.  `interp` (N, I): the linear interpolation from
    the tables' I incidences onto the engine's N cells, dK_k = dR_k (W^T x 1_c) (`_sector_kernels`), or
    None: the columns are the engine's cells already (I c = N c, dK_k = dR_k).  Twelve sectors of
    (M, N c, I c) are 0.23 GB per wavelength on the engine's default grid (0.46 GB on the engine's cells).
    `exits` (M, N c, O) SECTOR_EXIT_DTYPE: each sector's exit kernel minus the 0-deg one.

    Precision (why single precision is enough).  The differences are made in double precision and then
    rounded once to single (relative rounding 2^-24 = 6e-8 of each element); the products with them are
    taken in single precision and promoted (`apply`; `_rough_exit` promotes the exits).  They carry only
    the part of the field that differs from sector to sector, a fraction of the light inside the plate,
    so the rows change by at most ~1e-7 of their value (GMRES solves to 1e-7 relative anyway), while the
    tables they come from carry the Monte-Carlo noise of their rays, 1e-3 to 1e-1 per cell, and a
    recording's noise is ~1e-2: the rounding is five orders of magnitude below what the rows can tell.
    Measured on an anisotropic relief traced by rays (tests/backend/plate/test_sector_precision.py): the
    simulated rows move by under 1e-6 of their largest value against double-precision kernels, asserted
    < 1e-4 (the relief of that test: 7e-11 on the tables' incidences, 1e-10 on the engine's cells); the
    differences kept on the tables' incidences (`interp`) against the same differences on the engine's
    cells, both in double precision, move the rows by 2e-18 of the largest (rounding; asserted < 1e-9).  The sums that are not
    differences (the circulant loop's system and its LU factors, the 0-deg kernels) stay double: they
    carry the whole field."""

    azimuths_deg: np.ndarray
    loop: np.ndarray
    exits: tuple
    interp: np.ndarray | None = None

    def weighted(self, w: np.ndarray) -> np.ndarray:
        """sum_k w_k dK_k, (M, N c, N c) complex in the kernels' precision (summed in it; promoted where used)."""
        M, two_nc, kic = self.loop.shape
        nc = two_nc // 2
        ic = kic // len(w)
        r = (self.loop.reshape(M * two_nc, kic // ic, ic).transpose(0, 2, 1) @ np.asarray(w, self.loop.dtype))
        if self.interp is not None:                 # onto the engine's cells: (., I, c) -> W (., I, c) = (., N, c)
            r = self.interp.astype(self.loop.dtype) @ r.reshape(M * two_nc, self.interp.shape[1], -1)
        r = r.reshape(M, two_nc, nc)
        out = np.empty((M, nc, nc), np.result_type(self.loop.dtype, np.complex64))
        out.real, out.imag = r[:, :nc], r[:, nc:]
        return out

    def apply(self, Y: np.ndarray) -> np.ndarray:
        """sum_k dK_k Y_k for Y (K, M, N c, q) complex: (M, N c, q) complex.  With dK = R + i I and
        Y = a + i b: [R; I] [a b] = [[R a, R b], [I a, I b]], so Re = R a - I b and Im = R b + I a
        (Y first taken onto the tables' incidences, (W^T x 1_c) Y, where `interp` is given)."""
        K, M, nc, q = Y.shape
        if self.interp is not None:
            N, I = self.interp.shape
            Y = (self.interp.T @ Y.reshape(K, M, N, (nc // N) * q)).reshape(K, M, I * (nc // N), q)
        ic = Y.shape[2]
        ab = np.empty((M, K * ic, 2 * q), self.loop.dtype)
        Yt = np.moveaxis(Y, 0, 1).reshape(M, K * ic, q)
        ab[..., :q] = Yt.real
        ab[..., q:] = Yt.imag
        P = self.loop @ ab                                                                  # (M, 2 N c, 2 q)
        return (P[:, :nc, :q] - P[:, nc:, q:]).astype(float) + 1j * (P[:, :nc, q:] + P[:, nc:, :q])


@dataclass(frozen=True)
class SectorsHeader:
    """What a solver keeps of its inside sector table once the table's kernels exist for every wavelength it
    solves (`drop_sector_table`): the sector centres, the table's metadata and which of its wavelengths
    carry the same numbers (`same_at`, for `PlateSolver._twin_wavelength`); no cells."""

    phi_i_deg: np.ndarray
    wavelength_nm: np.ndarray
    metadata: dict
    same: frozenset            # (a_nm, b_nm) pairs whose rows are equal

    @staticmethod
    def of(table: BsdfTable) -> "SectorsHeader":
        w = [float(x) for x in np.asarray(table.wavelength_nm, float)]
        return SectorsHeader(np.asarray(table.phi_i_deg, float).copy(), np.asarray(w), dict(table.metadata),
                             frozenset((a, b) for a in w for b in w if table.same_at(a, b)))

    def same_at(self, a_nm: float, b_nm: float) -> bool:
        return (float(a_nm), float(b_nm)) in self.same
