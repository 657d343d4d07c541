"""The beam's miss term (docs/beam.md, "The miss term"): what a pose's explanation pays for a
landmark near one of its pixel observations' rays, surely within the camera's detection range,
that it leaves unclaimed.

A ray's pool holds every landmark near it; the pair cost c of the observation with one of them
(d^2 + ln det S - ln det R, twice a negative log-likelihood, inside the gate or not) against the
observation's null cost n (clutter) gives the chance that the observation is that landmark:
L = exp(-(c - n) / 2), p = L / (1 + L). Not detecting a landmark the camera detects with chance
p_D where it is has probability 1 - p_D p; the charge is twice its negative logarithm,
-2 ln(1 - p_D p), with p_D = 1 - exp(-miss_cost / 2) so that a sure miss (p = 1) costs miss_cost.
A flat miss_cost for every pool member lost the robot on 3 of 32 pixel-only worlds of seeds 5-8
(docs/performance.md, 2026-12-05).

Pure numpy ufuncs: the numpy beam (``camloc.beam_expansion``) applies them to arrays, the compiled
one (``camloc.kernels.beam``) compiles them for a scalar: one definition for both engines.
"""

import numpy as np

# (c - n) / 2 is clipped here: exp of more would overflow for far pairs, and p is 2e-22 already
EXCESS_CLIP = 50.0


def miss_charge(excess, miss_cost):
    """-2 ln(1 - p_D p): the cost of leaving unclaimed a landmark whose best pair in a pose's
    pools has ``excess`` (the pair's cost minus its observation's null cost), p = L / (1 + L) with
    L = exp(-excess / 2) the chance that the observation is that landmark rather than clutter,
    p_D = 1 - exp(-miss_cost / 2). Rises with p (so a landmark in several pools is charged at its
    smallest excess): about 2 p_D p for a small p, ``miss_cost`` at p = 1. Self-contained (a
    compiled function calls no plain Python one)."""
    p = 1.0 / (1.0 + np.exp(np.minimum(0.5 * excess, EXCESS_CLIP)))
    detection = 1.0 - np.exp(-0.5 * miss_cost)
    return -2.0 * np.log1p(-detection * p)
