"""The host's work in other processes: the estimator process (`estimate_worker`) and estimate
workers over Zenoh (`distribute`)."""
