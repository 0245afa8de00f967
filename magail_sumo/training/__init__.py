"""Training: discriminator objective (more to come: PPO with the GAIL reward, BC)."""
