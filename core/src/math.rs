//! Vendored f32 math (placeholder: being filled in).

#[inline(always)]
pub fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}

// TEMPORARY: libm-backed until the vendored versions land (these break GPU bit-exactness).
pub fn sqrt(x: f32) -> f32 {
    libm::sqrtf(x)
}
pub fn log(x: f32) -> f32 {
    libm::logf(x)
}
pub fn cos(x: f32) -> f32 {
    libm::cosf(x)
}
pub fn exp(x: f32) -> f32 {
    libm::expf(x)
}
