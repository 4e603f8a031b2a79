"""Task variants built on the path-tracking environment (one module per task).

``ball_on_plate`` and ``humanoid_balance`` add sensor feedback (paper 000 §IV-B);
``velocity_max`` is the velocity-maximisation experiment of paper 001.
"""
