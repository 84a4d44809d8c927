"""``python -m torchsim.evaluate``: runs the evaluation entry point, which lives with the recipes
(``torchsim.algos.evaluate``); the engine imports nothing of them."""

import runpy

if __name__ == "__main__":
    runpy.run_module("torchsim.algos.evaluate", run_name="__main__", alter_sys=True)
