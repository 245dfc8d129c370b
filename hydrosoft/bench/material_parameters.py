"""Names of the bubble material's parameters and of the contact models the material fit knows, without the model
library's imports (``hydrosoft-stack fit --help`` reads them)."""

PARAMETERS = ("E", "K", "mu")
UNITS = {"E": "Pa/m", "K": "Pa/m", "mu": ""}
MU_MAX = 3.0  # the fit keeps mu in (0, MU_MAX)
#: Contact models the fit replays through; one entry per model (``hydrosoft.contact.MODELS`` names).
FIT_MODELS = ("nh", "pf", "nh_pressure_normal")
#: How the fit reports its uncertainty (``fit --uncertainty``): the Gauss-Newton covariance at the optimum, a
#: parametric bootstrap (``fit_bootstrap``) or profile-likelihood intervals (``fit_profile``).
UNCERTAINTY_METHODS = ("hessian", "bootstrap", "profile")
BOOTSTRAP_INTERVALS = ("percentile", "basic")  # the bootstrap's 95 % intervals (``fit_bootstrap.intervals_of``)
DEFAULT_DRAWS = 100  # bootstrap refits
