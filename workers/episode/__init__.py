"""The episode side of an actor: an env and a policy stepped through one episode into rows.

``rows`` (the specs the driver sends and the typed rows it gets back: the driver/actor
contract), ``worker`` (the episode worker, in-process or as a Ray actor), ``observation`` (an
env's observation as a policy's), ``videos`` (episode videos). The policy it steps is
``workers.policy``'s (its wrapper in the actor, or the client of a shared policy actor).
"""
