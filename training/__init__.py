"""Offline training tools: the demonstration / DAgger recorder, the tiny VLA trainer, the zoo,
and the toy lerobot checkpoints (random weights) the tests and benchmarks build.

They import ``workers/`` (envs, experts, backbones) and are never imported by it or by
``pipeline/``: nothing here runs inside an evaluation.
"""
