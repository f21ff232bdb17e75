"""Offline training tools: the demonstration / DAgger recorder and the tiny VLA trainer.

They import ``workers/`` (envs, experts, backbones) and are never imported by it or by
``pipeline/``: nothing here runs inside an evaluation.
"""
