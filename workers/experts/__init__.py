"""Scripted experts: backbones that act from an env's privileged simulator state.

They know one env's internals, so they live here, not in ``backbones/`` (which never imports
an env) nor in ``envs/`` (which never holds a backbone); they import ``envs/`` only.
"""
