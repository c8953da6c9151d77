"""Software-in-the-loop simulation: flight model, scripted pilot and device byte generators."""
