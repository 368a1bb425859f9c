//! `loglio-fw`: the loglio core as Cortex-M firmware (QEMU mps2-an386, Cortex-M4F, 16 MiB).
//!
//! Reads a recording (see `loglio_firmware_sim::firmware_recording`) through semihosting, runs the odometry
//! of the firmware configuration over it with all its memory in one static pool (`.bss`, checked
//! against `memory.x` by the linker), and prints one pose line per scan (the f64 bits in hex) and
//! the SysTick ticks each `process_scan` took. Under `-icount shift=0` SysTick counts exactly one
//! tick per 40 instructions (25 MHz system clock, 1 ns per instruction), so the counts are
//! deterministic instruction budgets.
//!
//! ```text
//! cargo build -p loglio-firmware-sim --bin loglio-fw --profile firmware --target thumbv7em-none-eabihf
//! qemu-system-arm -M mps2-an386 -cpu cortex-m4 -nographic -monitor none -serial none \
//!   -icount shift=0 -semihosting-config enable=on,target=native \
//!   -kernel target/thumbv7em-none-eabihf/firmware/loglio-fw -append /abs/path/recording.bin
//! ```
//!
//! Exit codes: 0 done, 2 no argument or the file cannot be opened, 3 the recording is bad,
//! 4 the odometry configuration is rejected, 101 a panic.
//!
//! On hosted targets this is a stub that says how to build it.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "loglio-fw is Cortex-M firmware: cargo build -p loglio-firmware-sim --bin loglio-fw \
         --profile firmware --target thumbv7em-none-eabihf (see docs/firmware.md)"
    );
    std::process::exit(2);
}

#[cfg(target_os = "none")]
mod fw {
    use core::fmt::{self, Write as _};
    use core::sync::atomic::{AtomicU32, Ordering};

    use cortex_m::peripheral::SYST;
    use cortex_m::peripheral::syst::SystClkSource;
    use cortex_m_rt::{entry, exception};
    use loglio_core::scan::{ScanPoint, ScanView};
    use loglio_firmware_sim::firmware_recording::{self, FW_POINTS, Reader, Record};
    use semihosting::io::{Read as _, Write as _};
    use semihosting::{c, println};
    use static_cell::ConstStaticCell;

    #[cfg(not(feature = "oversized-pool"))]
    type Storage = firmware_recording::FirmwareStorage;
    /// 2^17 voxels (24 MiB): more than the board has; the link must fail.
    #[cfg(feature = "oversized-pool")]
    type Storage = loglio_core::odometry::OdometryStorage<
        { loglio_core::ring_fals::storage_pixels(firmware_recording::FW_ROWS, firmware_recording::FW_COLS) },
        FW_POINTS,
        { firmware_recording::FW_DOWNSAMPLE_SLOTS },
        { 1 << 17 },
        { 1 << 18 },
    >;

    /// Every byte of the odometry's memory: all zero, so it lands in `.bss` and the linker checks
    /// it against `memory.x`.
    static STORAGE: ConstStaticCell<Storage> = ConstStaticCell::new(Storage::new());
    /// The scan being replayed.
    static POINTS: ConstStaticCell<[ScanPoint; FW_POINTS]> = ConstStaticCell::new(
        [ScanPoint { xyz: [0.0; 3], t: 0.0, row: 0, col: 0, intensity: 0, ret: 0, flags: 0 }; FW_POINTS],
    );

    /// SysTick wraps (each 2^24 ticks).
    static WRAPS: AtomicU32 = AtomicU32::new(0);
    const RELOAD: u32 = 0x00FF_FFFF;

    #[exception]
    fn SysTick() {
        WRAPS.fetch_add(1, Ordering::Relaxed);
    }

    /// Ticks since SysTick started (64-bit, from the wrap count and the down-counter).
    fn ticks() -> u64 {
        loop {
            let w0 = WRAPS.load(Ordering::Relaxed);
            let cur = SYST::get_current();
            if WRAPS.load(Ordering::Relaxed) == w0 {
                return ((w0 as u64) << 24) + (RELOAD - cur) as u64;
            }
        }
    }

    /// The core's stage clock: SysTick ticks x 40, which under `-icount shift=0` is the number
    /// of instructions (and the virtual time in ns).
    struct TickClock;

    impl loglio_core::odometry::Clock for TickClock {
        fn now_ns(&mut self) -> u64 {
            ticks() * 40
        }
    }

    /// A semihosting file as an `embedded_io` reader.
    struct HostFile(semihosting::fs::File);

    #[derive(Debug)]
    struct HostError(semihosting::io::Error);

    impl fmt::Display for HostError {
        fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            write!(f, "semihosting read error {:?}", self.0)
        }
    }

    impl core::error::Error for HostError {}

    impl embedded_io::Error for HostError {
        fn kind(&self) -> embedded_io::ErrorKind {
            embedded_io::ErrorKind::Other
        }
    }

    impl embedded_io::ErrorType for HostFile {
        type Error = HostError;
    }

    impl embedded_io::Read for HostFile {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, HostError> {
            self.0.read(buf).map_err(HostError)
        }
    }

    /// One output line, written to semihosting stdout in one call.
    struct Line {
        buf: [u8; 1024],
        len: usize,
    }

    impl fmt::Write for Line {
        fn write_str(&mut self, s: &str) -> fmt::Result {
            let end = self.len + s.len();
            if end > self.buf.len() {
                return Err(fmt::Error);
            }
            self.buf[self.len..end].copy_from_slice(s.as_bytes());
            self.len = end;
            Ok(())
        }
    }

    impl Line {
        fn flush(&mut self) {
            let end = self.len.min(self.buf.len() - 1);
            self.buf[end] = b'\n';
            if let Ok(mut out) = semihosting::io::stdout() {
                let _ = out.write_all(&self.buf[..=end]);
            }
            self.len = 0;
        }
    }

    fn fail(code: i32, what: fmt::Arguments<'_>) -> ! {
        semihosting::eprintln!("loglio-fw: {what}");
        semihosting::process::exit(code)
    }

    #[entry]
    fn main() -> ! {
        // SysTick on the core clock, free-running, counting wraps in the exception.
        let Some(mut cp) = cortex_m::Peripherals::take() else { fail(1, format_args!("peripherals taken")) };
        cp.SYST.set_clock_source(SystClkSource::Core);
        cp.SYST.set_reload(RELOAD);
        cp.SYST.clear_current();
        cp.SYST.enable_interrupt();
        cp.SYST.enable_counter();

        let args = match semihosting::experimental::env::args::<1024>() {
            Ok(a) => a,
            Err(_) => fail(2, format_args!("no command line (pass the recording with -append)")),
        };
        // The first argument is the image; the recording is the last one.
        let mut path_buf = [0u8; 1024];
        let mut path_len = 0;
        for (i, a) in (&args).into_iter().enumerate() {
            if let (true, Ok(a)) = (i > 0, a)
                && a.len() < path_buf.len()
            {
                path_buf[..a.len()].copy_from_slice(a.as_bytes());
                path_len = a.len();
            }
        }
        if path_len == 0 {
            fail(2, format_args!("usage: loglio-fw RECORDING (QEMU: -append RECORDING)"));
        }
        let path = match core::ffi::CStr::from_bytes_until_nul(&path_buf[..=path_len]) {
            Ok(p) => p,
            Err(_) => fail(2, format_args!("bad path")),
        };
        let file = match semihosting::fs::File::open(path) {
            Ok(f) => f,
            Err(_) => fail(2, format_args!("cannot open {:?}", path)),
        };
        let (mut reader, header) = match Reader::new(HostFile(file)) {
            Ok(x) => x,
            Err(e) => fail(3, format_args!("bad recording: {e}")),
        };

        let storage = STORAGE.take();
        let points = POINTS.take();
        let cfg = firmware_recording::firmware_config(&header);
        let mut odo = match storage.odometry(&cfg) {
            Ok(o) => o,
            Err(e) => fail(4, format_args!("configuration rejected: {e}")),
        };
        println!(
            "loglio-fw: storage {} bytes ({} voxels), scan buffer {} bytes, ram {}",
            Storage::bytes(),
            firmware_recording::FW_POOL_VOXELS,
            core::mem::size_of::<[ScanPoint; FW_POINTS]>(),
            c!("mps2-an386 16 MiB").to_str().unwrap_or(""),
        );

        let mut line = Line { buf: [0; 1024], len: 0 };
        let (mut scans, mut imu) = (0u32, 0u32);
        let mut total_ticks = 0u64;
        loop {
            match reader.next_record(&mut points[..]) {
                Ok(Record::Imu(s)) => {
                    let _ = odo.push_imu(s);
                    imu += 1;
                }
                Ok(Record::Scan { start_ns, points: n }) => {
                    let t0 = ticks();
                    let r =
                        odo.process_scan_timed(ScanView { start_ns, points: &points[..n] }, &mut TickClock);
                    let dt = ticks() - t0;
                    total_ticks += dt;
                    let _ = firmware_recording::write_pose_line(&mut line, scans, &r);
                    line.flush();
                    // Whole call in ticks, then the stages in clock units (ticks x 40).
                    let st = &r.times;
                    let _ = write!(
                        line,
                        "ticks {scans} {dt} stages normals={} undistort={} downsample={} association={} update={} map={} points={}/{}",
                        st.normals_ns,
                        st.undistort_ns,
                        st.downsample_ns,
                        st.association_ns,
                        st.update_ns,
                        st.map_ns,
                        r.points[0],
                        r.points[1]
                    );
                    line.flush();
                    scans += 1;
                }
                Ok(Record::End) => break,
                Err(e) => fail(3, format_args!("bad recording after {scans} scans: {e}")),
            }
        }
        let _ = write!(line, "done scans={scans} imu={imu} ticks={total_ticks}");
        line.flush();
        semihosting::process::exit(0)
    }
}
