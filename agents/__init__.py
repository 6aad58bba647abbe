"""astrocargo.agents: reference trajectories (``trajectories``), the team's rigid-body kernels
(``team_dynamics``: composite body, desired wrench, allocation) and the scripted cooperative
controllers built on them (``controllers``)."""
