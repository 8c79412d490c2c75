"""What ROS 2 sees of the cell: the topics, types and hashes (``types``), the run's
messages as ROS 2 messages (``convert``), rmw_zenoh's keys, tokens and attachments
(``wire``) and rosbag2 bags of a run's recordings (``bag``)."""

BAGS_DIR = "rosbag2"  # where etar-bench export --rosbag2 writes a run's bags by default: RUN_DIR/rosbag2/
