"""Planning: the protocols planners depend on, the objective, GPC-RANK / OPT / RANK+OPT and the prior-free baselines."""
