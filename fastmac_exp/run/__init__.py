"""The experiment machinery around the flow of one pair: the command line (cli), launch checks (checks,
sweep_check), the loop over a dataset's pairs (experiment), the results table (results) and what makes a run
safe to interrupt and share (resume, runlock), Hydra callbacks (callbacks, sweep_summary) and the Ray
launcher's job function (ray_launch)."""
