"""Recordings: one MCAP file per episode, what crossed the wire, and what reads it back.

``format`` (the layout and its one error), ``writer`` (``EpisodeWriter``), ``offload``
(the same writer in a helper process, for an in-process run), ``reader``
(``read_episode``, truncated files included), ``demonstrations`` (a recording as
the learner's arrays, with ``etar.features``), ``recovery`` (a truncated file made
whole).  Imports the runtime's messages and visual topic registry.
"""
