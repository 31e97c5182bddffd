"""Fusion-node simulator: routes, speed profile, raw sensors, DR/GPS Kalman filter, drives."""
