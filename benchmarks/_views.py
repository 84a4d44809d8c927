"""World cameras that frame each env's model, shared by ``benchmarks/bench_render.py`` and ``scripts/check_cuda.py``:
env name -> (eye, target) for ``torchsim.render.Camera.look_at``, in metres."""

VIEW = {"ant": ((2.5, -2.5, 2.0), (0.0, 0.0, 0.4)), "humanoid": ((3.0, -3.0, 2.0), (0.0, 0.0, 1.0)),
        "reacher": ((0.3, -0.35, 0.35), (0.0, 0.0, 0.0)), "grasp": ((12.0, -12.0, 10.0), (0.0, 0.0, 3.0))}
