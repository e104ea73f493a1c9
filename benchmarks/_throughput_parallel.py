"""Helpers of ``write_throughput.py`` that run in spawned processes (importable by module name).

``bare_cast_processes``: the bare Open3D cast (``create_rays_pinhole`` + ``cast_rays``) of a list of frames
split into contiguous halves over ``n`` processes, each with its own BVH of the same mesh, started together
after a barrier: the floor of what ``n`` cores give a user of Open3D alone.  ``timed_render_block``: the
``render.sequence.render_block`` returning the worker's CPU seconds (all its threads) spent on the block.
"""
from __future__ import annotations

import multiprocessing
import time

import numpy as np


def _bare_worker(vertices, faces, K, width, height, poses, frames, barrier, queue) -> None:
    import open3d as o3d

    origin = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor((vertices - origin).astype(np.float32)),
                     o3d.core.Tensor(faces.astype(np.uint32)))
    Kt = o3d.core.Tensor(K)

    def one(i: int):
        pose = np.array(poses[i], dtype=np.float64)
        pose[:3, 3] -= origin
        rays = rc.create_rays_pinhole(Kt, o3d.core.Tensor(np.linalg.inv(pose)), width, height)
        return rc.cast_rays(rays)["t_hit"].numpy()

    if frames:
        one(frames[0])                                            # warm-up
    barrier.wait()
    t0, c0 = time.perf_counter(), time.process_time()
    for i in frames:
        one(i)
    queue.put((t0, time.perf_counter(), time.process_time() - c0, len(frames)))


def bare_cast_processes(scene, frames: list[int], n: int) -> dict:
    """``n`` processes, contiguous parts of ``frames``; wall = first start to last end, CPU = their sum."""
    ctx = multiprocessing.get_context("spawn")
    barrier, queue = ctx.Barrier(n), ctx.Queue()
    parts = [list(a) for a in np.array_split(np.asarray(frames), n)]
    cam = scene.camera
    procs = [ctx.Process(target=_bare_worker, args=(scene.mesh.vertices, scene.mesh.faces, cam.K, cam.width,
                                                    cam.height, np.asarray(scene.poses), [int(x) for x in part],
                                                    barrier, queue)) for part in parts]
    for pr in procs:
        pr.start()
    res = [queue.get() for _ in procs]
    for pr in procs:
        pr.join()
    return {"wall_s": max(r[1] for r in res) - min(r[0] for r in res), "cpu_s": sum(r[2] for r in res),
            "frames": sum(r[3] for r in res)}


def timed_render_block(state: dict, block: tuple[int, int]) -> tuple[list, float]:
    """``render_block`` and the CPU seconds this process spent on it (its writes are done when it returns)."""
    from room_pipeline.render.sequence import render_block as _render_block

    c0 = time.process_time()
    out = _render_block(state, block)
    return out, time.process_time() - c0
