"""Measurements of the simulation, each apart from its report.

``stability`` (exact amplification theory), ``omega`` (a model's ω_max), ``under_load`` (the states a run
reaches), ``damping`` (the damping of its modes) and ``advisor`` (the pre-run advisor, built on them),
``watch`` (the advisor during a run, a frame hook), ``modal`` (the float64 modal reference), ``load_battery``
(the advisor under load), ``stability_map`` (measured stable steps) and ``stability_map_report``;
``trade`` (error against cost of every integrator) with ``trade_problems``, ``trade_choice`` and
``trade_report``; sweeps (``sweep``, ``sweep_plan``, ``sweep_batch``, ``engines``, ``sweep_ray``,
``sweep_report``); ``audit`` (float64 collision audits); ``softbody_elasticity``; ``analytic`` (closed forms
the measurements compare against).
"""
