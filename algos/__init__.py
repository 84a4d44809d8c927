"""Training algorithms; the PPO/SAC training recipes arrive with the training issue."""
