"""Planning: camera trajectories along the airway centreline graph (pure functions, no file I/O)."""
