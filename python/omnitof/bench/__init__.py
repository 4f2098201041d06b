"""Experiments: many SLAM runs (inputs × presets × a grid of settings × seeds) on Dask.

`experiment` reads and plans an experiment file, `inputs` says how inputs reach the workers (and
makes the simulated ones), `task` is one run on a worker (the code of `omnitof slam`),
`runner` drives the cluster, `folders` keeps the experiment's folder (one results folder per
run; what is complete), `table` makes the table and figures from those folders alone.
docs/guide/bench.md is the user's guide. Dask is imported only when an experiment runs.
"""

from omnitof.bench.experiment import Experiment, ExperimentError, RunSpec, load_experiment, plan_runs

__all__ = ["Experiment", "ExperimentError", "RunSpec", "load_experiment", "plan_runs"]
