"""hydra/launcher=ray_cluster: each sweep member as one Ray task on a running cluster (ray_launcher)."""
