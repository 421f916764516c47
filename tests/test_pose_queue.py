"""The server's Zenoh session queues up to ``ZenohConf.pose_queue`` (16) poses per link
instead of Zenoh's 2 (config.py says why: on a busy machine, poses leaving at once towards
one peer were dropped without a word, and a client waited forever for its last frame's
answer). A Zenoh config file that sets the queues itself keeps its own."""

from __future__ import annotations

import json

from sfmloc.server.config import ZenohConf
from sfmloc.server.zenoh_io import POSE_QUEUE_KEY, server_zenoh_config


def test_the_server_queues_sixteen_poses_per_link_unless_its_zenoh_file_says_otherwise(tmp_path):
    import zenoh

    assert json.loads(zenoh.Config().get_json(POSE_QUEUE_KEY)) == 2  # Zenoh's own
    conf = server_zenoh_config(ZenohConf(multicast=False))
    assert json.loads(conf.get_json(POSE_QUEUE_KEY)) == 16
    assert json.loads(server_zenoh_config(ZenohConf(pose_queue=4)).get_json(POSE_QUEUE_KEY)) == 4
    own = tmp_path / "zenoh.json5"
    own.write_text(
        "{ transport: { link: { tx: { queue: { size: { real_time: 3 } } } } } }\n", "utf-8"
    )
    conf = server_zenoh_config(ZenohConf(config_file=str(own)))
    assert json.loads(conf.get_json(POSE_QUEUE_KEY)) == 3
    plain = tmp_path / "plain.json5"
    plain.write_text("{ scouting: { multicast: { enabled: false } } }\n", "utf-8")
    conf = server_zenoh_config(ZenohConf(config_file=str(plain)))
    assert json.loads(conf.get_json(POSE_QUEUE_KEY)) == 16
