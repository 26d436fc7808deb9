"""The RealSense D435: live, playback and recording."""
