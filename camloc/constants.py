"""Fixed constants (not options) that both engines read, defined once: the beam's, read by the
numpy beam (``camloc.beam``: ``BeamSettings``' defaults), the compiled one's settings
(``camloc.scene``) and its seed search (``camloc.seeds``, ``camloc.kernels.beam``), and the
iterated update's (``camloc.ekf``, ``camloc.kernels.update``). Plain Python: no numba import, so
the numpy engine reads them without loading the kernels. The reason for each beam value is in
``docs/beam.md``."""

from camloc.tails import chi2_quantile

# Hypotheses whose states differ by less than this many standard deviations on every axis merge.
MERGE_SIGMA = 0.3
# Most partial explanations of a pose kept across all the beam's hypotheses, past each one's best.
PARTIAL_BUDGET = 64
# A pose whose observations are all rays (pixels; at least one) giving at most SPARSE_ROWS_PER_DIM
# measurement rows per dimension of the state (a pixel gives 2: 6 of them for the 6-dof state) is a
# sparse pose (``camloc.sparse_poses``; a pose with a point-giving observation, depth, disparity, a
# tag or a planar one, never is): it barely over-determines the state, so a wrong
# explanation of it costs little more than the right one and the ambiguity lasts over the poses
# after it; its beam keeps up to SPARSE_WIDTH_FACTOR times the width, SPARSE_DELTA_EXTRA more cost
# units (16: the right one kept at e^-8 of the best's likelihood), but each extra hypothesis (past
# the run's width and delta) at least SPARSE_DISTINCT_SIGMA standard deviations from every kept one
# on some axis, and only while the poses stay sparse. Measured: docs/performance.md, 2026-12-06
# (eleventh session, issue35-sparse; twelfth, issue35-sparse2; thirteenth, issue35-sparse3: rays only).
SPARSE_ROWS_PER_DIM = 2
SPARSE_WIDTH_FACTOR = 3
SPARSE_DELTA_EXTRA = 16.0
SPARSE_DISTINCT_SIGMA = 2.0

# A hypothesis conditioned on some of a pose's pairs re-gates each remaining observation among the
# landmarks that were within this many gates before: its predictions moved by about H dx, with dx
# drawn from the variance it lost, so a landmark it gates was within the (wider) earlier gate with
# the same probability; twice the gate (about 99.996% for the default) makes a miss negligible.
POOL_GATE_FACTOR = 2.0

# A chain of a pose's pair updates is checked against the pose's prior (``camloc.beam_chain``,
# ``camloc.kernels.beam_chain``) only where that prior is wide for the rays: where some pixel
# observation's cheapest option has (H P H')_aa / (f_a sigma_a) beyond this on its u or v row. That
# ratio is a pinhole's second-order term over one standard deviation of the prior (along or across
# the ray, or a turn: about the first-order spread squared over f) in standard deviations of the
# noise: the error of a pair linearized that far from where the chain ends. A chain's MAP cost
# passes its 99.9% chi^2 bound through such an error only where it passes the bound's margin over a
# pixel pair's mean, sqrt(chi^2_2(99.9%) - 2) = 3.4 standard deviations: below it the check is
# not run (on a default-noise pixel world the ratio's median is 0.9 and its 99th percentile 7.5; on
# the 3x worlds of docs/performance.md its 10th percentile is 20).
RAY_NONLINEARITY = float(chi2_quantile(2, 0.001) - 2.0) ** 0.5

# The slip's search runs at a pose of at least this many observations, most of them unassigned: two
# detections with depth pin the position and two of the three rotation axes, with the prior the third.
SLIP_MIN_OBSERVATIONS = 2
# The slip's search: pairs ranked as first pairs, seeds explained in full, explanations kept per seed.
SLIP_CANDIDATES = 256
SLIP_SEEDS = 8
SEED_EXPLANATIONS = 2

# The slip's search runs where a pose's best explanation leaves an unusual share of its observations
# unassigned for this data: a binomial tail below UNUSUAL_PROBABILITY at the rate of the last
# UNEXPLAINED_WINDOW poses' best explanations (at most UNEXPLAINED_RATE_CAP), for the pose alone or
# pooled with the UNEXPLAINED_RUN - 1 poses before it.
UNEXPLAINED_WINDOW = 50
UNUSUAL_PROBABILITY = 0.01
UNEXPLAINED_RATE_CAP = 0.6
UNEXPLAINED_RUN = 3
# The plain seeded search also runs at a pose whose best explanation leaves at most half its
# observations unassigned, where at least SEEDED_MIN_UNASSIGNED of them are and that many is this
# unlikely for the pose alone: one wrong pair taken first can pull the state off the others' right
# landmarks, leaving them unassigned (docs/beam.md, "The seeded search's trigger"). Two left is
# what a clutter detection and a missed pair commonly give: from two, the search ran at 2.9% of
# the 20k benchmark world's poses and cost it 0.7-1.2 s; from three, at about half as many, and
# the consistency it bought on issue 36's worlds is the same.
SEEDED_UNUSUAL_PROBABILITY = 0.05
SEEDED_MIN_UNASSIGNED = 3

# A seeded explanation whose state leaves its prior's 99.9% region is dropped: the chi^2 quantile
# with 6 degrees of freedom.
STATE_GATE = float(chi2_quantile(6, 0.001))

# A view widened for a wide prior (the seeds' search) reaches this many standard deviations of the
# prior's position (metres) and orientation (angle) further; no view's half-angle passes
# MAX_HALF_ANGLE_DEG from the optical axis (the widened one, or the one estimated from the data).
WIDENED_VIEW_SIGMAS = 3.0
MAX_HALF_ANGLE_DEG = 89.0

# Two shifts of the robot that a pose's pairs imply agree (a Hough vote for the seeds) within
# AGREEMENT_SIGMAS standard deviations of a measured point, plus AGREEMENT_DEPTH_FRACTION of its
# depth for the orientation's error (about 6 deg).
AGREEMENT_SIGMAS = 3.0
AGREEMENT_DEPTH_FRACTION = 0.1

# Iterated updates stop when the correction changes by less than this (metres / radians).
CONVERGED = 1e-6
# The beam's update of a branched child's one ray (a pixel pair: ``kernels.beam.settle``,
# ``beam_expansion.PoseExpansion.paired_state``) also stops once a linearization moved the state by
# less than this many of its prior's standard deviations on every axis, the iterated EKF's usual
# rule in the prior's metric: Gauss-Newton there contracts about tenfold a step, so the next
# linearization would move it by about a tenth of that (on the 20k pixel world, where the second
# moved it less than 3e-2 prior sigma, the third moved it less than 1e-3 in 98% and never 1e-2),
# far below the 0.3 sigma at which the beam merges hypotheses. The filter's own update and the
# beam's stacked and depth updates keep ``CONVERGED`` alone. Measured: docs/performance.md,
# 2026-12-07 (eighteenth session, pixel-speed4).
RAY_STEP_SIGMA = 0.03

# The most linearizations one update may take: the --iterations setting's upper limit, and the damped
# Gauss-Newton's of an update whose MAP cost is beyond its chi^2 bound (ekf.damped_gauss_newton,
# kernels/update.py damped_start; docs/filter.md): a bound on the work, not on the estimate (from a
# prior as wide as the landmarks' depth it reaches the MAP estimate in 4-10).
MAX_LINEARIZATIONS = 50

# The damped Gauss-Newton of an update beyond its chi^2 bound (ekf.damped_gauss_newton, kernels/update.py
# damped_start) is Levenberg-Marquardt's, damped in the prior's metric: a step solves
# (P^-1 (1 + damping) + H' R^-1 H) step = gradient; the damping starts at DAMPING_START, is multiplied by 10
# for each step that does not lower the MAP cost (at most DAMPING_RAISES times a linearization: to 1e-15
# of the Gauss-Newton step), and divided by 10 after each that does. Marquardt's usual start and factor.
DAMPING_START = 1e-3
DAMPING_RAISES = 15

# What a pose's explanation pays for a landmark surely on a pixel observation's ray, surely within its
# camera's detection range (observation_space.detection_range), that it leaves unclaimed; one less sure
# on the ray pays less (the beam's miss term: camloc.miss_term, camloc.beam_expansion, kernels/beam.py
# expected_landmarks and missed; docs/beam.md).
MISS_COST = 8.0

# An alternative to an update this many cost units above it weighs under 2e-9 of it: what the chance
# that a pair is clutter adds to the estimate's covariance leaves it out (ekf.leave_one_out_spread,
# kernels/recheck.py add_leave_one_out_spread), as it does a right pair's, most of a run's.
NEGLIGIBLE_MARGIN = 40.0

# The re-check's drops of rays against leaving them unassigned are weighed together, every subset of
# them restored or not (association.restored_pairs, kernels/recheck.py restored_pairs), up to this many
# a pose (2^4 joint costs); beyond it they stay dropped.
RESTORE_LIMIT = 4
