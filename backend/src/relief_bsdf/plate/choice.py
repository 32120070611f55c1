"""Which physics a relief face uses: the relief's own method (`auto`) resolved once per relief.

`DEFAULT_METHOD = "auto"` is the one default boundary method of `relief simulate`, `relief fit`
and `relief diagnose` (paper sec. 3 step 2: the boundary BSDF derived from the measured relief
by the proper solution): `methods.auto.choose` picks ray tracing with inter-reflections for
reliefs rough on the wavelength scale and wave optics (Kirchhoff, Rayleigh-Rice) for smooth
ones, from the relief's statistics against the wavelength, for light from outside AND inside
(the inside index is the stricter case for the wave conditions).  The fast surrogates
(`microfacet+dw`, `flat`) stay available by name, never as the default.

The choice is made ONCE on the relief as given (the file's relief, before the fit's scale and
filter), then fixed: a fit whose objective switched physics between two evaluations would see a
jump, not a valley.  The resolved face records the choice (`ReliefFace.chosen_by`), so every
output says which physics was used and why.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from relief_bsdf.plate.description import Experiment
from relief_bsdf.plate.faces import ReliefFace
from relief_bsdf.plate.grid import TableGrid

from relief_bsdf.defaults import METHOD as DEFAULT_METHOD   # the one default method (CLI, panel)


def resolve_face(face: Any, material: Any, grid: TableGrid, wavelengths_nm: Any, theta_i_outside_deg: Any) -> Any:
    """`face` with method "auto" replaced by auto's choice for this relief, material, wavelengths and
    incidences (`ReliefFace.resolved`; other faces and resolved relief faces are returned unchanged)."""
    if not isinstance(face, ReliefFace):
        return face
    return face.resolved(material, grid, wavelengths_nm, theta_i_outside_deg)


def resolve_auto(experiment: Experiment, rows: Any, grid: TableGrid | None = None) -> Experiment:
    """The experiment with every `auto` relief face resolved for these recording rows (module doc)."""
    grid = grid or TableGrid()
    p = experiment.plate
    wl = np.unique(np.asarray(rows.wavelength_nm, float))
    ti = np.unique(np.asarray(rows.theta_i_deg, float))
    front = resolve_face(p.front, p.material, grid, wl, ti)
    back = resolve_face(p.back, p.material, grid, wl, ti)
    if front is p.front and back is p.back:
        return experiment
    return experiment.with_plate(front=front, back=back)


def chosen_lines(experiment: Experiment) -> list[str]:
    """The auto choices recorded on the experiment's faces (one line each; empty when none)."""
    return [f.chosen_by for f in (experiment.plate.front, experiment.plate.back)
            if isinstance(f, ReliefFace) and f.chosen_by]
