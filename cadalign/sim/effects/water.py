"""Water optical properties for the revised underwater image formation model.

Akkaynak & Treibitz (CVPR 2018, "A Revised Underwater Image Formation Model")::

    I_c = J_c exp(-beta_D_c z) + B_inf_c (1 - exp(-beta_B_c z))

with ``z`` the range along the line of sight, ``beta_D`` the wideband attenuation
of the direct signal, ``beta_B`` the (different) wideband backscatter coefficient
and ``B_inf`` the veiling light, per R, G, B channel.

The Jerlov presets are approximations, good for plausible simulation, not for
radiometry:

* ``beta_D`` is Jerlov's diffuse downwelling attenuation ``K_d`` (Jerlov 1976,
  *Marine Optics*, 2nd ed., Table XXVII; the water types of Solonenko & Mobley
  2015, Appl. Opt. 54(17), and the proxy for ``beta_D`` used by Akkaynak et al.
  2017/2018), linearly interpolated at 620 / 540 / 460 nm for R / G / B.
* ``beta_B`` is taken as the beam attenuation ``c = a + b ~ K_d + b`` (Akkaynak &
  Treibitz 2018 show ``beta_B`` is governed by ``c``), with the scattering
  ``b = b_w (550/l)^4.32 + b_p(550) (550/l)``; ``b_p(550)`` per type is a rough
  value: ``0.3 Chl^0.62`` (Gordon & Morel 1983) at a typical chlorophyll for the
  oceanic types, order-of-magnitude coastal turbidity for 1C-9C.
* ``B_inf`` is single-scattering veiling light ``~ b / c`` tinted by down-welling
  light that crossed 5 m of the same water, scaled so its brightest channel is
  ``0.3 b/c`` of the clean render's white.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.errors import ConfigError

_JERLOV_NM = np.arange(400.0, 701.0, 25.0)
# Jerlov (1976) Table XXVII: K_d (1/m) at 400, 425, ..., 700 nm.
_JERLOV_KD: dict[str, tuple[float, ...]] = {
    "I": (0.027, 0.022, 0.019, 0.018, 0.027, 0.043, 0.063, 0.089, 0.235, 0.305, 0.36, 0.42, 0.56),
    "IA": (0.038, 0.031, 0.026, 0.025, 0.032, 0.048, 0.067, 0.094, 0.24, 0.31, 0.37, 0.43, 0.57),
    "IB": (0.051, 0.042, 0.036, 0.033, 0.042, 0.054, 0.072, 0.099, 0.245, 0.315, 0.375, 0.435, 0.58),
    "II": (0.096, 0.081, 0.068, 0.062, 0.07, 0.076, 0.089, 0.115, 0.26, 0.335, 0.4, 0.465, 0.61),
    "III": (0.185, 0.16, 0.135, 0.116, 0.115, 0.116, 0.12, 0.148, 0.295, 0.375, 0.445, 0.52, 0.66),
    "1C": (0.51, 0.36, 0.25, 0.17, 0.14, 0.13, 0.12, 0.15, 0.3, 0.37, 0.45, 0.51, 0.65),
    "3C": (0.78, 0.54, 0.39, 0.29, 0.22, 0.2, 0.19, 0.21, 0.33, 0.4, 0.46, 0.56, 0.71),
    "5C": (1.1, 0.78, 0.56, 0.43, 0.36, 0.31, 0.3, 0.33, 0.4, 0.48, 0.54, 0.65, 0.8),
    "7C": (1.6, 1.2, 0.89, 0.71, 0.58, 0.49, 0.46, 0.46, 0.48, 0.54, 0.63, 0.78, 0.92),
    "9C": (2.4, 1.9, 1.6, 1.23, 0.99, 0.78, 0.63, 0.58, 0.6, 0.65, 0.76, 0.92, 1.1),
}
# Particle scattering b_p at 550 nm (1/m): rough, see the module docstring.
_PARTICLE_B550 = {"I": 0.03, "IA": 0.07, "IB": 0.11, "II": 0.22, "III": 0.39,
                  "1C": 0.5, "3C": 0.8, "5C": 1.2, "7C": 1.8, "9C": 2.5}
JERLOV_TYPES: tuple[str, ...] = tuple(_JERLOV_KD)
"""The Jerlov water types accepted by :func:`water_from_jerlov`, clearest first (oceanic I-III, coastal 1C-9C)."""
RGB_NM = (620.0, 540.0, 460.0)
"""Wavelengths (nm) standing in for the R, G, B channels."""
_PURE_WATER_B550 = 0.0019
_VEIL_DEPTH_M = 5.0
_VEIL_LEVEL = 0.3


def _rgb3(value: object, name: str) -> np.ndarray:
    arr = np.array(value, dtype=np.float32)
    if arr.shape != (3,):
        raise ConfigError(f"WaterParams.{name} must have 3 values (R, G, B), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"WaterParams.{name} must be finite, got {arr.tolist()}")
    if np.any(arr < 0):
        raise ConfigError(f"WaterParams.{name} must be >= 0 per channel, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class WaterParams:
    """Per-channel (R, G, B) water coefficients of the revised model; all >= 0.

    Attributes:
        beta_D: (3,) attenuation of the direct signal, 1/m.
        beta_B: (3,) backscatter coefficient, 1/m.
        B_inf: (3,) veiling light (backscatter at infinite range), linear radiance.
    """

    beta_D: np.ndarray
    beta_B: np.ndarray
    B_inf: np.ndarray

    def __post_init__(self) -> None:
        for name in ("beta_D", "beta_B", "B_inf"):
            object.__setattr__(self, name, _rgb3(getattr(self, name), name))

    @staticmethod
    def clear() -> WaterParams:
        """No attenuation, no backscatter (a vacuum or perfectly clear water)."""
        return WaterParams(np.zeros(3), np.zeros(3), np.zeros(3))


def water_from_jerlov(name: str) -> WaterParams:
    """Approximate R, G, B water coefficients for a Jerlov water type.

    Args:
        name: one of :data:`JERLOV_TYPES` (I, IA, IB, II, III, 1C, 3C, 5C, 7C, 9C).

    Returns:
        The water parameters (see the module docstring for how each is derived).

    Raises:
        ConfigError: unknown water type.

    Example:
        >>> w = water_from_jerlov("I")
        >>> bool(w.beta_D[0] > w.beta_D[2])  # red attenuates faster than blue in clear ocean
        True
    """
    if name not in _JERLOV_KD:
        raise ConfigError(f"unknown Jerlov water type {name!r}; allowed values: {', '.join(JERLOV_TYPES)}")
    nm = np.array(RGB_NM)
    kd = np.interp(nm, _JERLOV_NM, np.array(_JERLOV_KD[name]))
    b = _PURE_WATER_B550 * (550.0 / nm) ** 4.32 + _PARTICLE_B550[name] * (550.0 / nm)
    c = kd + b
    tint = np.exp(-kd * _VEIL_DEPTH_M)
    b_inf = _VEIL_LEVEL * (b / c) * tint / tint.max()
    return WaterParams(kd, c, b_inf)


def jerlov_table() -> dict[str, WaterParams]:
    """Every Jerlov preset, by name (for reports and docs)."""
    return {name: water_from_jerlov(name) for name in JERLOV_TYPES}
