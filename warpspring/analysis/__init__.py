"""Measurements of the simulation, each apart from its report.

``stability`` (exact amplification theory), ``omega`` (a model's ω_max), ``under_load`` (the states a run
reaches), ``damping`` (the damping of its modes) and ``advisor`` (the pre-run advisor, built on them),
``watch`` (the advisor during a run), ``stability_map`` (measured stable steps) and ``stability_map_report``; ``trade`` (error against cost of every integrator) and
``trade_report``; ``analytic`` (closed forms the measurements compare against).
"""
