"""What Foxglove shows of a run: the visual scene (``scene``), fed from the wire
(``tap``), and the export that adds the visual topics to finished recordings
(``export``); the live view's door for viewers that offer only the protocol's old
name (``door``).  The topics' names and schemas live in ``services.runtime.visual_topics``.
"""
