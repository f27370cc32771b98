"""What every run of the library needs around its training, ``isodream-train``'s and ``isodream-video``'s alike:
checkpoints, the run folder's lock, disk space, CSV logs cut back on resume."""
