"""Measurements of the simulation, each apart from its report.

``stability`` (exact amplification theory and the pre-run advisor), ``stability_map`` (measured stable
steps) and ``stability_map_report``; ``trade`` (error against cost of every integrator) and
``trade_report``; ``analytic`` (closed forms the measurements compare against).
"""
