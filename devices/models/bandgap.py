"""InGaN films: band gap from composition, indium incorporation from growth temperature, and a DFT estimate.

- Band gap of In(x)Ga(1-x)N with bowing, Wu et al., Appl. Phys. Lett. 80, 4741
  (2002): Eg(x) = 3.42 (1 - x) + 0.77 x - 1.43 x (1 - x) eV.
- Indium incorporation falls with growth temperature as indium desorbs: the
  film's indium fraction is the nominal one times 1 / (1 + exp((T - 780 °C) / 40 °C))
  (a logistic stand-in for the steep loss above ~750 °C reported for MOCVD
  growth; the constants are ours).
- The DFT calculator sees only the nominal composition (no growth physics), with
  a systematic +0.12 eV offset and 0.05 eV random error: within the ±0.2 eV a
  hybrid-functional calculation typically achieves, and wrong in a way only
  experiments can correct.
"""

from __future__ import annotations

import math

EG_GAN, EG_INN, BOWING = 3.42, 0.77, 1.43
DFT_OFFSET_EV, DFT_SD_EV = 0.12, 0.05


def band_gap_ev(x: float) -> float:
    return EG_GAN * (1 - x) + EG_INN * x - BOWING * x * (1 - x)


def incorporated(x_nominal: float, growth_temperature_c: float) -> float:
    return x_nominal / (1 + math.exp((growth_temperature_c - 780.0) / 40.0))


def film_band_gap_ev(x_nominal: float, growth_temperature_c: float) -> float:
    return band_gap_ev(incorporated(x_nominal, growth_temperature_c))


def dft_band_gap_ev(x_nominal: float, noise: float) -> float:
    """What the calculator reports; ``noise`` is a standard normal draw."""
    return band_gap_ev(x_nominal) + DFT_OFFSET_EV + DFT_SD_EV * noise
