"""The one set of defaults of the command line and the Blender panel (no imports: both read it).

METHOD: the boundary method when none is named (`plate.choice.DEFAULT_METHOD`): the relief's
own physics, chosen from its statistics. WAVELENGTHS_NM, THETA_I_DEG: the tables' default
wavelengths and incidences, 0-89 deg so a table reaches grazing light (the bake and the plate's
loop read the last incidence for everything beyond it). SAMPLES: Monte-Carlo paths per
incidence of the ray methods. SEED: the random seed.
"""
METHOD = "auto"
WAVELENGTHS_NM = (550.0,)
THETA_I_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 89.0)
SAMPLES = 200_000
SEED = 0


def as_text(values) -> str:
    """Comma-separated values as the CLI and the panel write them: 0,10,...,89."""
    return ",".join(f"{v:g}" for v in values)
