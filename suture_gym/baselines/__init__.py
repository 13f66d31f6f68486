"""Baselines for suture_gym: Stable-Baselines3 training/evaluation helpers and the scripted expert.

Needs the ``train`` extra (torch CPU build first, then stable-baselines3 and sb3-contrib).
"""
