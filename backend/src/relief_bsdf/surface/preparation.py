"""What is done to a height map between reading it and using it, as the user asked.

`ReliefOptions` collects the choices a user can state for a map (CLI flags `--crop`,
`--downsample`, `--fill-holes`, `--periodic/--no-periodic`; sample.toml keys
`[relief] periodic` and `fill_holes`); `prepare_relief` applies them in a fixed order:

1. crop (`Relief.cropped`): a window X0,Y0,W,H in points (x = column, y = row);
2. downsample (`Relief.downsampled`): k x k block means;
3. periodicity (`surface.periodicity.decide_periodicity`): the user's statement, else not
   periodic for a cropped or trimmed map (a window of a map is not a period of it; the
   wrap-around test cannot tell a window from a tile when the correlation length is a pixel
   or two), else the file's statement, else the wrap-around test;
4. fill holes (`Relief.fill_holes`): harmonic interpolation of every missing point (a
   periodic tile's holes see their neighbours across the wrap).

Every step lands in the relief's history, so outputs can state what was done.
"""
from __future__ import annotations

from dataclasses import dataclass

from relief_bsdf.errors import InputError
from relief_bsdf.surface.periodicity import Periodicity, decide_periodicity, with_periodicity


@dataclass(frozen=True)
class ReliefOptions:
    """crop: (x0, y0, width, height) in points or None; downsample: block size k >= 1;
    fill_holes: fill every missing point first; periodic: True / False as stated, None = decide;
    stated_by: who stated `periodic` / `fill_holes`, for the logs."""

    crop: tuple[int, int, int, int] | None = None
    downsample: int = 1
    fill_holes: bool = False
    periodic: bool | None = None
    stated_by: str = "the command line"

    def overridden(self, other: "ReliefOptions") -> "ReliefOptions":
        """These options with every choice `other` states (a non-default value) taking precedence."""
        return ReliefOptions(crop=other.crop if other.crop is not None else self.crop,
                             downsample=other.downsample if other.downsample != 1 else self.downsample,
                             fill_holes=self.fill_holes or other.fill_holes,
                             periodic=other.periodic if other.periodic is not None else self.periodic,
                             stated_by=other.stated_by if other.periodic is not None else self.stated_by)


def parse_crop(text: str) -> tuple[int, int, int, int]:
    """`X0,Y0,W,H` (whole numbers of points, W and H >= 2) -> tuple; InputError naming --crop."""
    try:
        v = tuple(int(s) for s in str(text).split(","))
    except ValueError:
        v = ()
    if len(v) != 4 or v[0] < 0 or v[1] < 0 or v[2] < 2 or v[3] < 2:
        raise InputError("--crop", f"expected X0,Y0,W,H in points (X0, Y0 >= 0; W, H >= 2), got {text!r}")
    return v  # type: ignore[return-value]


def crop_window(relief, crop: tuple[int, int, int, int]):
    """`relief` cut to the window (x0, y0, w, h); InputError when it leaves the map."""
    x0, y0, w, h = crop
    ny, nx = relief.shape
    if x0 + w > nx or y0 + h > ny:
        raise InputError(relief.source or "relief", f"crop {x0},{y0},{w},{h} (X0,Y0,W,H) leaves the map of "
                                                    f"{nx} x {ny} points (x along columns, y along rows)")
    return relief.cropped(slice(y0, y0 + h), slice(x0, x0 + w))


def prepare_relief(relief, options: ReliefOptions):
    """The relief after crop, downsample, the periodicity decision and hole filling (module docstring)."""
    trimmed = options.crop is not None or any(k % options.downsample for k in relief.shape)
    if options.crop is not None:
        relief = crop_window(relief, options.crop)
    if options.downsample != 1:
        relief = relief.downsampled(options.downsample)
    if options.periodic is not None:
        p = decide_periodicity(relief, options.periodic, options.stated_by)
    elif trimmed:
        p = Periodicity(False, "crop", "a window cut out of the map (or trimmed to whole blocks) is not a period "
                                       "of it; --periodic / [relief] periodic = true says otherwise")
    else:
        p = decide_periodicity(relief)
    relief = with_periodicity(relief, p)
    if options.fill_holes and not relief.valid.all():
        relief = relief.fill_holes()                  # after the decision: a periodic tile's holes wrap
    return relief
