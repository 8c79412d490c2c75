"""The words a model and its users share: what ETAR's state and features can be (with
their columns), which transition models there are and which criteria choose the number
of phases.  Plain Python, so that a scenario can check them without loading the learner."""

STATES = {"position": 3, "pose": 6}  # pose: position and rotation vector
FEATURES = {"force": 3, "force_torque": 6}
TRANSITIONS = ("effect", "state")  # effect: ETAR (features from the force); state: STAR
CRITERIA = ("bic", "aic")
# a phase per distinct contact of the task: the thesis' tasks need at most 6 (docs/learning.md);
# many more than that, fitted on a handful of demonstrations, is a typo that fails at learning
MAX_PHASES = 20
