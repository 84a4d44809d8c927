"""``python -m torchsim.train``: runs the training entry point, which lives with the recipes
(``torchsim.algos.train``); the engine imports nothing of them."""

import runpy

if __name__ == "__main__":
    runpy.run_module("torchsim.algos.train", run_name="__main__", alter_sys=True)
