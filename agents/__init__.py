"""astrocargo.agents."""
