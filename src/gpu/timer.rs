//! GPU timestamp queries: named marks in a command buffer, read back as milliseconds per pass.

use super::{Gpu, Result};
use ash::vk;

pub struct GpuTimer {
    gpu: Gpu,
    pool: vk::QueryPool,
    capacity: u32,
    names: Vec<&'static str>,
}

impl GpuTimer {
    pub fn new(gpu: &Gpu, capacity: u32) -> Result<GpuTimer> {
        // SAFETY: a plain timestamp pool of this device; the timer owns it and destroys it in Drop.
        let pool = unsafe {
            gpu.device.create_query_pool(
                &vk::QueryPoolCreateInfo::default()
                    .query_type(vk::QueryType::TIMESTAMP)
                    .query_count(capacity),
                None,
            )?
        };
        Ok(GpuTimer {
            gpu: gpu.clone(),
            pool,
            capacity,
            names: Vec::new(),
        })
    }

    /// Resets the pool and writes the first (start) mark.
    pub fn begin(&mut self, cmd: vk::CommandBuffer) {
        self.names.clear();
        // SAFETY: `cmd` is recording outside a render pass (the caller's contract); queries
        // 0..capacity are this pool's.
        unsafe {
            self.gpu
                .device
                .cmd_reset_query_pool(cmd, self.pool, 0, self.capacity)
        };
        self.mark(cmd, "start");
    }

    /// Marks the end of the pass `name` (everything since the previous mark).
    pub fn mark(&mut self, cmd: vk::CommandBuffer, name: &'static str) {
        let idx = self.names.len() as u32;
        if idx >= self.capacity {
            return;
        }
        self.names.push(name);
        // SAFETY: `cmd` is recording (the caller's contract); `idx` < `capacity` was checked above.
        unsafe {
            self.gpu.device.cmd_write_timestamp2(
                cmd,
                vk::PipelineStageFlags2::ALL_COMMANDS,
                self.pool,
                idx,
            )
        };
    }

    /// (pass name, milliseconds) for every mark after the first; call after the work finished.
    pub fn read(&self) -> Result<Vec<(&'static str, f64)>> {
        let n = self.names.len();
        if n < 2 {
            return Ok(Vec::new());
        }
        let mut ticks = vec![0u64; n];
        // SAFETY: queries 0..n were reset and written by the recorded begin/mark calls (the caller
        // reads after that submission, so WAIT returns); `ticks` holds n u64 values as TYPE_64
        // asks.
        unsafe {
            self.gpu.device.get_query_pool_results(
                self.pool,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )?;
        }
        let ns = self.gpu.timestamp_period as f64;
        Ok((1..n)
            .map(|i| {
                let dt = ticks[i].saturating_sub(ticks[i - 1]);
                (self.names[i], dt as f64 * ns * 1e-6)
            })
            .collect())
    }
}

impl Drop for GpuTimer {
    fn drop(&mut self) {
        // SAFETY: the pool is this timer's own; its owners drop it once the command buffers that
        // wrote it finished.
        unsafe { self.gpu.device.destroy_query_pool(self.pool, None) }
    }
}
