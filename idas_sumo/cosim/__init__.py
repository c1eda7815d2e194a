"""Co-simulation: SUMO's own traffic through a merge, a share of it driven by a policy, and flow statistics.

``demand`` reads what the command line says (vehicles per hour per road, penetration rates); ``control``
drives the automated cars with the engine's pieces (snapshot, masks, policies); ``stats`` reads what SUMO
measured; ``run`` is one run; ``study`` the resumable grid of runs behind ``idas-sumo cosim``.
"""
