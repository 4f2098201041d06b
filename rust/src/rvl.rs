//! RVL, the lossless depth-image coding of A. D. Wilson, "Fast lossless depth image
//! compression", ISS 2017, which ROS's compressed_depth_image_transport offers beside PNG.
//!
//! The stream is a sequence of 4-bit codes packed into 32-bit little-endian words, the first
//! code in a word's top four bits. A number is written in codes of 3 bits each, least
//! significant first, with the code's top bit set while more follow. The pixels come as runs:
//! the number of zeros (no reading), the number of non-zeros that follow, then each non-zero
//! as the zigzag-coded difference to the non-zero before it ((d << 1) ^ (d >> 31)).
//!
//! Decoding is a loop over every pixel, hence here; errors are returned, never panicked on: a
//! stream that ends early, a number longer than 32 bits, or runs beyond the image.

/// The pixels (row-major, `pixels` of them) of an RVL stream.
pub fn decode(data: &[u8], pixels: usize) -> Result<Vec<u16>, String> {
    let mut codes = Codes { data, next: 0, word: 0, left: 0 };
    let mut out = Vec::new();
    out.try_reserve_exact(pixels).map_err(|_| format!("no memory for {pixels} pixels"))?;
    let mut previous: i64 = 0;
    while out.len() < pixels {
        let zeros = codes.number()?;
        let room = pixels - out.len();
        if zeros > room as u64 {
            return Err(format!("a run of {zeros} zeros at pixel {} runs past the image's {pixels} pixels", out.len()));
        }
        out.resize(out.len() + zeros as usize, 0);
        let nonzeros = codes.number()?;
        if nonzeros > (pixels - out.len()) as u64 {
            return Err(format!(
                "a run of {nonzeros} readings at pixel {} runs past the image's {pixels} pixels",
                out.len()
            ));
        }
        for _ in 0..nonzeros {
            let zigzag = codes.number()? as i64;
            let delta = (zigzag >> 1) ^ -(zigzag & 1);
            // The coder took differences of 16-bit values: they wrap as those do.
            previous = (previous + delta).rem_euclid(1 << 16);
            out.push(previous as u16);
        }
    }
    Ok(out)
}

/// The RVL stream of `pixels`, coded as the paper gives it: for test data and benchmarks (the
/// project reads RVL images; it writes none).
pub fn encode(pixels: &[u16]) -> Vec<u8> {
    let mut words: Vec<u32> = Vec::new();
    let (mut word, mut written) = (0u32, 0u32);
    let mut put = |value: u64| {
        let mut value = value;
        loop {
            let mut code = (value & 0x7) as u32;
            value >>= 3;
            if value != 0 {
                code |= 0x8;
            }
            word = (word << 4) | code;
            written += 1;
            if written == 8 {
                words.push(word);
                word = 0;
                written = 0;
            }
            if value == 0 {
                break;
            }
        }
    };
    let (mut i, mut previous) = (0usize, 0i64);
    while i < pixels.len() {
        let zeros = pixels[i..].iter().take_while(|&&p| p == 0).count();
        put(zeros as u64);
        i += zeros;
        let nonzeros = pixels[i..].iter().take_while(|&&p| p != 0).count();
        put(nonzeros as u64);
        for &p in &pixels[i..i + nonzeros] {
            let delta = (p as i64 - previous) as i32;
            put(((delta << 1) ^ (delta >> 31)) as u32 as u64);
            previous = p as i64;
        }
        i += nonzeros;
    }
    if written > 0 {
        words.push(word << (4 * (8 - written)));
    }
    words.iter().flat_map(|w| w.to_le_bytes()).collect()
}


/// The 4-bit codes of the stream, in order.
struct Codes<'a> {
    data: &'a [u8],
    next: usize,
    word: u32,
    left: u32,
}

impl Codes<'_> {
    fn code(&mut self) -> Result<u32, String> {
        if self.left == 0 {
            let bytes = self
                .data
                .get(self.next..self.next + 4)
                .ok_or_else(|| format!("the stream ends early, after {} bytes", self.data.len()))?;
            self.word = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
            self.next += 4;
            self.left = 8;
        }
        let code = self.word >> 28;
        self.word <<= 4;
        self.left -= 1;
        Ok(code)
    }

    /// One number: 3 bits per code, least significant first, while the code's top bit is set.
    fn number(&mut self) -> Result<u64, String> {
        let (mut value, mut shift) = (0u64, 0u32);
        loop {
            let code = self.code()?;
            value |= u64::from(code & 0x7) << shift;
            if code & 0x8 == 0 {
                return Ok(value);
            }
            shift += 3;
            if shift > 32 {
                return Err(format!("a number longer than 32 bits at byte {}", self.next));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_a_stream_worked_by_hand() {
        // [0, 0, 5]: 2 zeros (code 2), 1 reading (code 1), 5 as zigzag 10 = 0b1010: codes
        // 0b1010 (2, more to come) and 0b0001. One word 0x21A1_0000, little-endian.
        assert_eq!(decode(&[0x00, 0x00, 0xA1, 0x21], 3).unwrap(), vec![0, 0, 5]);
        assert_eq!(encode(&[0, 0, 5]), vec![0x00, 0x00, 0xA1, 0x21]);
    }

    #[test]
    fn round_trips_depth_images() {
        let mut state = 12345u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        for _ in 0..20 {
            let n = 1 + (next() % 5000) as usize;
            let pixels: Vec<u16> = (0..n)
                .map(|_| match next() % 4 {
                    0 => 0,
                    1 => u16::MAX - (next() % 3) as u16,
                    _ => 300 + (next() % 7000) as u16,
                })
                .collect();
            assert_eq!(decode(&encode(&pixels), n).unwrap(), pixels);
        }
        assert_eq!(decode(&encode(&[0; 100]), 100).unwrap(), vec![0; 100]);
        assert_eq!(decode(&[], 0).unwrap(), Vec::<u16>::new());
    }

    #[test]
    fn refuses_broken_streams_without_panicking() {
        let stream = encode(&[7, 8, 9, 0, 0, 10]);
        assert!(decode(&stream[..stream.len() - 4], 6).unwrap_err().contains("ends early"));
        assert!(decode(&stream, 4).unwrap_err().contains("runs past"));
        assert!(decode(&[0xFF; 16], 10).unwrap_err().contains("longer than 32 bits"));
        assert!(decode(&[1, 2, 3], 1).unwrap_err().contains("ends early"));
    }
}
