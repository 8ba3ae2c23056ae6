"""Who may do what, from where and how often: tokens and roles, Host and Origin checks, frame
and calibration budgets.
"""
