"""Every JSON Schema a recording carries is one that every Foxglove generation reads: an
object always says its ``properties`` (Foxglove Studio 1.48 rejects an object schema
without them, "Cannot convert undefined or null to object", and then cannot plot the
topic), down to the items of arrays and the nested fields."""

from __future__ import annotations

import json

from services.runtime.messages import MESSAGES
from services.runtime.visual_topics import SCHEMA_NAMES, schema_bytes


def objects_without_properties(schema, where="") -> list[str]:
    found = []
    if isinstance(schema, dict):
        if schema.get("type") == "object" and "properties" not in schema:
            found.append(where or "/")
        for key, value in schema.items():
            found += objects_without_properties(value, f"{where}/{key}")
    elif isinstance(schema, list):
        for i, value in enumerate(schema):
            found += objects_without_properties(value, f"{where}/{i}")
    return found


def test_every_message_schema_says_the_properties_of_its_objects():
    bad = {m.topic: objects_without_properties(m.json_schema()) for m in MESSAGES.values()}
    assert not {k: v for k, v in bad.items() if v}
    # the ones the viewer was seen to reject
    episode = MESSAGES["episode_summary"].json_schema()["properties"]
    assert episode["hold"]["properties"] == {} and episode["fri"]["type"] == "object"


def test_every_visual_schema_says_the_properties_of_its_objects():
    for topic in SCHEMA_NAMES:
        assert objects_without_properties(json.loads(schema_bytes(topic))) == [], topic
