"""Unit factors shared by calibd's modules: SI inside, display units at the edges."""

import math

from .frames import STANDARD_GRAVITY

DEG = math.pi / 180  # rad per deg
RAD_S_TO_DEG_H = 3600 / DEG  # deg/h per rad/s
M_S2_TO_MG = 1000 / STANDARD_GRAVITY  # mg per m/s^2
SQRT_S_PER_SQRT_H = 60.0  # a random walk per sqrt(s) is 60 times that per sqrt(h)
