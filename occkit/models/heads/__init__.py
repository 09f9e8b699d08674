"""Prediction heads on BEV features: occupancy (channel-to-height) and CenterPoint detection."""
