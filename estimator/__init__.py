"""astrocargo.estimator."""
