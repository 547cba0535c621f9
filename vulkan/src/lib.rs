//! Vulkan backend for himap (under construction).
