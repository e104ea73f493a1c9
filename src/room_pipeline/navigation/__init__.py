"""Vision-based navigation of the simulated scope (issue #19).

perception.py   depth -> camera-frame point cloud, median scaling of a relative estimator to ground truth
planner.py      the sampling-based local planner (constant-curvature arc chains, cross-entropy method)
lumen.py        distances to the TRUE lumen surface (Open3D), for scoring plans and episodes
demo.py         the paper's single-frame demonstration (`room navigate demo`)
closed_loop.py  closed-loop episodes in the PyBullet simulator, policies and the oracle / darkest baselines
depth_source.py what the closed loop's depth policy plans on: gt or a depth estimator on the loop's (noisy) RGB
cli.py          the `room navigate` tool
"""
