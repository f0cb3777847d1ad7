"""What both stages' training loops share: schedule, metrics log, devices, resume, checkpoint files, DDP."""
