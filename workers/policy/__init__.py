"""The policy side of an actor: where a policy lives and how requests reach it.

``wrapper`` (the IDR wrapper over a backbone: its passes and the refinement), ``forward_shape``
(forwards of one fixed shape), ``service`` (the shared policy service: batched requests of many
episodes), ``actor`` (its Ray actor and the client an episode holds), and the actor's own socket:
``socket_messages`` (what travels), ``socket_settings`` (the run's token, the limits, the
endpoint), ``socket_server`` and ``socket_client``. Nothing here imports ``workers.episode``.
"""
