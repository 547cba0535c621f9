// Written by himap-shader-build with the module beside it; do not edit.
/// Entry points of the module, in module order.
pub const ENTRY_POINTS: &[&str] = &["ray_train_cs", "sdf_query_cs", "adam_check_cs", "loss_check_cs", "pixel_loss_cs", "pixel_rays_cs", "ray_render_cs", "step_count_cs", "color_query_cs", "loop_canary_cs", "mlp_forward_cs", "pixel_depth_cs", "grid_forward_cs", "pixel_backward_cs", "sample_forward_cs", "sample_backward_cs", "fixed_accumulate_cs", "sample_backward_wg_cs", "adam_cs", "probe_cs", "divide_cs"];
/// `NoContraction` decorations in the module.
pub const NO_CONTRACTION_DECORATIONS: usize = 6211;
