//! himap host library: dataset loaders, synthetic scenes, evaluation metrics, mesh extraction,
//! file outputs and a multi-threaded CPU backend around `himap-core`.
