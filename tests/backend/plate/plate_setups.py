"""The engine's setup of a plate whose boundary tables a test gives (`PlateSolver` / `simulate_rows` take the
tables; the Experiment's faces are flat placeholders): the Experiment built from the physics named."""
from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace
from relief_bsdf.plate.description import SOURCE_Q, Bulk
from relief_bsdf.plate.setup import EngineSetup


def plate_setup(thickness_m=2e-3, index=ConstantIndex(1.5), polarization="unpolarized", absorption_per_m=0.0,
                detector_half_angle_deg=1.0, tilt_deg=0.0, rough_face="front", **engine) -> EngineSetup:
    """An EngineSetup of an Experiment (thickness, index, bulk absorption, source polarisation "s" / "p" /
    "unpolarized", detector cone, tilt) and the engine's choices (`engine`: azimuth_cells, inside_interpolation,
    stokes_loop ...)."""
    q = SOURCE_Q[polarization] if isinstance(polarization, str) else float(polarization)
    ex = Experiment(Plate(thickness_m, index, FlatFace(), FlatFace(), Bulk(absorption_per_m=absorption_per_m)),
                    Instrument(detector_half_angle_deg=detector_half_angle_deg, polarization_q=q, tilt_deg=tilt_deg))
    return EngineSetup(ex, rough_face=rough_face, **engine)


def relief_experiment(setup: EngineSetup, relief) -> Experiment:
    """The setup's Experiment with `relief` on its rough face, traced by rays (the photon engine's plate)."""
    return setup.experiment.with_plate(**{setup.rough_face: ReliefFace(relief, method="ray")})
