"""Unit factors shared by calibd's modules: SI inside, display units at the edges."""

import math

from .frames import STANDARD_GRAVITY

DEG = math.pi / 180  # rad per deg
RAD_S_TO_DEG_H = 3600 / DEG  # deg/h per rad/s
M_S2_TO_MG = 1000 / STANDARD_GRAVITY  # mg per m/s^2
SQRT_S_PER_SQRT_H = 60.0  # a random walk per sqrt(s) is 60 times that per sqrt(h)

NO_SIGMA_DECIMALS = 4  # an estimate without a 1-sigma (the thesis's chains): the data rarely say more


def value_sigma_texts(value: float, sigma: float | None) -> tuple[str, str | None]:
    """A value and its 1-sigma as text, both rounded where the sigma's second significant digit
    is (further digits are noise); without a usable sigma, the value at NO_SIGMA_DECIMALS and None."""
    usable = sigma is not None and math.isfinite(sigma) and sigma > 0
    decimals = min(max(1 - math.floor(math.log10(sigma)), 0), 9) if usable else NO_SIGMA_DECIMALS
    return fixed(value, decimals), f"{sigma:.{decimals}f}" if usable else None


def fixed(value: float, decimals: int) -> str:
    """`value` to `decimals` decimals; a -0.0000 as 0.0000 (it says nothing a 0 does not)."""
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


def value_sigma(value: float, sigma: float | None, unit: str) -> str:
    """`value +- sigma unit` (value_sigma_texts), or `value unit` without a sigma."""
    value_text, sigma_text = value_sigma_texts(value, sigma)
    return f"{value_text} +- {sigma_text} {unit}" if sigma_text else f"{value_text} {unit}"


def estimate_rows(estimates) -> list[str]:
    """One aligned line per estimate (objects with value, sigma, unit, quality, by name): the
    name, the value and `+- sigma` right-aligned at their rounding (value_sigma_texts), the unit,
    and the quality in brackets when one is set."""
    texts = {name: value_sigma_texts(e.value, e.sigma) for name, e in estimates.items()}
    name_width = max((len(name) for name in estimates), default=0)
    value_width = max((len(v) for v, _ in texts.values()), default=0)
    sigma_width = max((len(s) for _, s in texts.values() if s), default=0)
    rows = []
    for name, e in estimates.items():
        value, sigma = texts[name]
        sigma = f" +- {sigma:>{sigma_width}}" if sigma else " " * (sigma_width + 4) if sigma_width else ""
        quality = f"  ({e.quality})" if e.quality else ""
        rows.append(f"{name:<{name_width}}  {value:>{value_width}}{sigma} {e.unit}{quality}")
    return rows
