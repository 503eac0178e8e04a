"""Gradio and the Hugging Face hub client stay off the network (imported before Gradio).

Gradio sends usage analytics and checks for a newer version unless told not to, and its
``huggingface_hub`` dependency may look models up; the app needs none of it, and a closed
network would make each attempt wait. Values a user set in the environment are kept.
"""

import os

os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_HUB_DISABLE_TELEMETRY", "1")
