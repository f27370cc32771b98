"""What every program of the library that trains needs around its training, ``isodream-train``'s RL and world-model
runs and ``isodream-video train``'s alike, below both: checkpoints (:mod:`~isodream_rl.run_utils.checkpoint`), the
run folder and its lock (:mod:`~isodream_rl.run_utils.run_folder`, :mod:`~isodream_rl.run_utils.run_lock`), disk
space (:mod:`~isodream_rl.run_utils.disk_space`), CSV logs cut back on resume (:mod:`~isodream_rl.run_utils.csv_logs`),
the first SIGINT/SIGTERM as "checkpoint, then stop" (:mod:`~isodream_rl.run_utils.signals`), the device check
(:mod:`~isodream_rl.run_utils.device`) and strict JSON for the results, absent scores as ``null``
(:mod:`~isodream_rl.run_utils.json_io`)."""
