"""The estimator: numpy and OpenCV (scipy where it earns it); no rclpy, messages or rosbags."""
# np.median imports numpy.ma on its first call: 25-35 ms inside the first frame a node
# processes, enough to put a 30 Hz stream a frame behind. Imported here, at start-up.
import numpy.ma  # noqa: F401
