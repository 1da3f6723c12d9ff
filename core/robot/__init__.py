"""The robot: its contract, the UR3's kinematics, the workspace guard, the ur_rtde backend and
the UR controller simulator it is tested against.

Takes flange poses ``tool_to_base`` (mm) to move to; gives the pose stream the arm reports.
"""
