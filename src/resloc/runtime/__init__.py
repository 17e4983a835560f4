"""The distributed runtime: every robot its own process, talking over Eclipse Zenoh.

Modules: :mod:`~resloc.runtime.messages` (the authenticated frames) and
:mod:`~resloc.runtime.schema` (their bodies),
:mod:`~resloc.runtime.transport` (Zenoh sessions), and the processes
:mod:`~resloc.runtime.world_process`, :mod:`~resloc.runtime.radio`,
:mod:`~resloc.runtime.robot`, :mod:`~resloc.runtime.recorder`, supervised by
:mod:`~resloc.runtime.swarm`. Robots run :class:`~resloc.cl.node.RobotNode`; nothing here
re-implements an equation. Needs the ``swarm`` extra (``eclipse-zenoh``, ``msgpack``);
``docs/runtime.md`` documents the protocol.
"""
