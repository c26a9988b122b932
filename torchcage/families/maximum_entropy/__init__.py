"""Maximum entropy coordinates with a mean value prior: ``api`` and ``module``."""
