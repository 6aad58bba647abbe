"""astrocargo.envs."""
