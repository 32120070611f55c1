"""Synthetic reliefs for the wave-optics tests (periodic, isotropic, Gaussian autocovariance).

Uses relief_bsdf.surface.synth.random_relief when it exists; otherwise FFT-filtered white Gaussian
noise with autocovariance s^2 exp(-r^2/L^2), i.e. PSD pi s^2 L^2 exp(-(pi L f)^2), the
convention of NIST SCATMECH's Gaussian_PSD_Function.  Heights are rescaled to the exact rms.
"""
import numpy as np

from relief_bsdf.surface.relief import Relief


def gaussian_relief(n: int, pitch_m: float, rms_m: float, corr_m: float, seed: int = 0) -> Relief:
    try:  # the project's generator, when it has landed
        from relief_bsdf.surface.synth import random_relief
        return random_relief(n, pitch_m, rms_m, corr_m, "gaussian", seed)
    except ImportError:
        pass
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n, pitch_m)
    fr2 = f[None, :] ** 2 + f[:, None] ** 2
    amp = np.sqrt(np.pi * corr_m ** 2 * np.exp(-(np.pi * corr_m) ** 2 * fr2))
    h = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * amp))
    h -= h.mean()
    h *= rms_m / h.std()
    return Relief(h, pitch_m, pitch_m, periodic=True, source="synthetic gaussian")


def scatmech_psd_bsdf(kind: int, wavelength_um: float, n: float, rms_um: float, corr_um: float,
                      theta_i_deg: float, theta_s_deg, phi_s_table_deg):
    """pySCATMECH microroughness BSDF at table directions (our phi -> SCATMECH phi + 180)."""
    from pySCATMECH.brdf import BRDF_Model
    m = BRDF_Model("Microroughness_BRDF_Model", wavelength=wavelength_um, substrate=n, type=kind,
                   psd={None: "Gaussian_PSD_Function", "sigma": rms_um, "length": corr_um})
    return np.array([m.BRDF(np.radians(theta_i_deg), np.radians(ts), np.radians(ps - 180.0))
                     for ts, ps in zip(np.ravel(theta_s_deg), np.ravel(phi_s_table_deg))])
