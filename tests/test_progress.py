"""The console names what ``torch.compile`` compiles, even after ``torch._dynamo.reset()`` (which clears dynamo's
compile callbacks, so an earlier test or script that resets must not silence the training run's announcements)."""

import logging

import torch

import torchsim.progress


class Doubler(torch.nn.Module):
    def forward(self, x):
        return 2 * x


def test_compiles_are_announced_by_name_after_a_dynamo_reset(caplog):
    torchsim.progress.announce_torch_compiles()
    torch._dynamo.reset()
    torchsim.progress.announce_torch_compiles()
    torchsim.progress.announce_torch_compiles()  # a second call registers nothing more: one announcement
    module = torch.compile(Doubler(), backend="eager")
    with caplog.at_level(logging.INFO, logger="torchsim"):
        assert torch.equal(module(torch.ones(3)), torch.full((3,), 2.0))
    started = [r.getMessage() for r in caplog.records if r.getMessage().startswith("compiling ")]
    assert len(started) == 1 and started[0].startswith("compiling Doubler.forward (torch.compile"), started
