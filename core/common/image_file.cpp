#include "common/image_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <opencv2/imgcodecs.hpp>
#include <vector>

#include "common/error.hpp"

namespace posecal {

namespace {

constexpr const char* kFormats = "PNG, JPEG, BMP, PNM, TIFF, WebP or Sun raster";

[[noreturn]] void broken(const char* format, const std::string& why) {
  throw Error(ErrorCode::kInvalidArgument, std::string("broken ") + format + " header: " + why);
}

uint32_t be16(const uint8_t* p) { return (uint32_t{p[0]} << 8) | p[1]; }
uint32_t le16(const uint8_t* p) { return (uint32_t{p[1]} << 8) | p[0]; }
uint32_t be32(const uint8_t* p) { return (be16(p) << 16) | be16(p + 2); }
uint32_t le32(const uint8_t* p) { return (le16(p + 2) << 16) | le16(p); }
uint64_t be64(const uint8_t* p) { return (uint64_t{be32(p)} << 32) | be32(p + 4); }
uint64_t le64(const uint8_t* p) { return (uint64_t{le32(p + 4)} << 32) | le32(p); }

ImageFileInfo info(const char* format, int64_t w, int64_t h) {
  if (w <= 0 || h <= 0) broken(format, "zero or negative width or height");
  return {format, w, h};
}

// Reads exactly n bytes or fails with `format`'s broken-header error.
void need(const ByteReader& read, uint64_t offset, void* buf, size_t n, const char* format) {
  if (read(offset, buf, n) != n) broken(format, "the file ends inside the header");
}

// JPEG: the first frame header (SOFn) after the markers before it; never past the scan data.
ImageFileInfo jpeg(const ByteReader& read) {
  uint64_t off = 2;
  for (int i = 0; i < 1'000'000; ++i) {
    uint8_t m[2];
    need(read, off, m, 2, "JPEG");
    if (m[0] != 0xFF) broken("JPEG", "no marker at offset " + std::to_string(off));
    if (m[1] == 0xFF) {  // fill byte
      ++off;
      continue;
    }
    const uint8_t code = m[1];
    off += 2;
    if (code == 0x01 || code == 0xD8 || (code >= 0xD0 && code <= 0xD7)) continue;  // no length
    if (code == 0xD9 || code == 0xDA) broken("JPEG", "no frame header before the image data");
    uint8_t seg[7];
    need(read, off, seg, 2, "JPEG");
    const uint32_t length = be16(seg);
    if (length < 2) broken("JPEG", "segment length below 2");
    const bool frame = code >= 0xC0 && code <= 0xCF && code != 0xC4 && code != 0xC8 && code != 0xCC;
    if (frame) {
      need(read, off, seg, 7, "JPEG");
      if (be16(seg + 3) == 0) broken("JPEG", "height given after the scan (DNL) is not supported");
      return info("JPEG", be16(seg + 5), be16(seg + 3));
    }
    off += length;
  }
  broken("JPEG", "too many markers before the frame header");
}

ImageFileInfo bmp(const uint8_t* h, size_t n) {
  if (n < 26) broken("BMP", "the file ends inside the header");
  const uint32_t dib = le32(h + 14);
  if (dib == 12) return info("BMP", le16(h + 18), le16(h + 20));
  if (dib < 36) broken("BMP", "unknown info header size " + std::to_string(dib));
  const int64_t w = static_cast<int32_t>(le32(h + 18));
  const int64_t height = static_cast<int32_t>(le32(h + 22));
  return info("BMP", w, height < 0 ? -height : height);  // negative: rows top-down
}

// The next whitespace-separated token of a PNM header, skipping '#' comments.
std::string pnm_token(const uint8_t* h, size_t n, size_t* pos) {
  while (*pos < n) {
    const char c = static_cast<char>(h[*pos]);
    if (c == '#') {
      while (*pos < n && h[*pos] != '\n') ++*pos;
    } else if (std::isspace(static_cast<unsigned char>(c))) {
      ++*pos;
    } else {
      break;
    }
  }
  std::string t;
  while (*pos < n && !std::isspace(h[*pos]) && h[*pos] != '#' && t.size() < 32)
    t.push_back(static_cast<char>(h[(*pos)++]));
  return t;
}

int64_t pnm_number(const std::string& t, const char* format) {
  if (t.empty() || t.size() > 12 || t.find_first_not_of("0123456789") != std::string::npos) {
    broken(format, "'" + t + "' is not a size");
  }
  return std::stoll(t);
}

ImageFileInfo pnm(const uint8_t* h, size_t n) {
  size_t pos = 2;
  if (h[1] != '7') {
    const char* format = h[1] == 'f' || h[1] == 'F' ? "PFM" : "PNM";
    const int64_t w = pnm_number(pnm_token(h, n, &pos), format);
    return info(format, w, pnm_number(pnm_token(h, n, &pos), format));
  }
  int64_t w = -1, height = -1;
  for (int i = 0; i < 64; ++i) {  // PAM: "KEY value" lines up to ENDHDR
    const std::string key = pnm_token(h, n, &pos);
    if (key.empty() || key == "ENDHDR") break;
    if (key == "WIDTH") w = pnm_number(pnm_token(h, n, &pos), "PAM");
    if (key == "HEIGHT") height = pnm_number(pnm_token(h, n, &pos), "PAM");
  }
  if (w < 0 || height < 0) broken("PAM", "no WIDTH or HEIGHT");
  return info("PAM", w, height);
}

// TIFF and BigTIFF: ImageWidth (256) and ImageLength (257) of the first directory, the image
// cv::imread decodes.
ImageFileInfo tiff(const ByteReader& read, const uint8_t* h) {
  const bool le = h[0] == 'I';
  const bool big = (le ? le16(h + 2) : be16(h + 2)) == 43;
  auto u16 = [le](const uint8_t* p) { return le ? le16(p) : be16(p); };
  auto u32 = [le](const uint8_t* p) { return le ? le32(p) : be32(p); };
  auto u64 = [le](const uint8_t* p) { return le ? le64(p) : be64(p); };
  uint8_t head[16];
  need(read, 0, head, big ? 16 : 8, "TIFF");
  if (big && (u16(head + 4) != 8 || u16(head + 6) != 0))
    broken("TIFF", "BigTIFF offsets are not 8 bytes");
  const uint64_t dir = big ? u64(head + 8) : u32(head + 4);
  uint8_t count_bytes[8];
  need(read, dir, count_bytes, big ? 8 : 2, "TIFF");
  const uint64_t count = big ? u64(count_bytes) : u16(count_bytes);
  if (count == 0 || count > 4096)
    broken("TIFF", "first directory has " + std::to_string(count) + " entries");
  const size_t entry = big ? 20 : 12;
  std::vector<uint8_t> entries(count * entry);
  need(read, dir + (big ? 8 : 2), entries.data(), entries.size(), "TIFF");
  int64_t w = -1, height = -1;
  for (uint64_t i = 0; i < count; ++i) {
    const uint8_t* e = entries.data() + i * entry;
    const uint32_t tag = u16(e), type = u16(e + 2);
    const uint8_t* value = e + (big ? 12 : 8);
    int64_t v = -1;
    if (type == 3) v = u16(value);                                     // SHORT
    if (type == 4) v = u32(value);                                     // LONG
    if (type == 16 && big)
      v = static_cast<int64_t>(std::min<uint64_t>(u64(value), 1ull << 62));  // LONG8
    if (tag == 256) w = v;
    if (tag == 257) height = v;
  }
  if (w < 0 || height < 0) broken("TIFF", "no ImageWidth or ImageLength in the first directory");
  return info("TIFF", w, height);
}

ImageFileInfo webp(const uint8_t* h, size_t n) {
  if (n < 30) broken("WebP", "the file ends inside the header");
  if (std::memcmp(h + 12, "VP8 ", 4) == 0) {
    if (h[23] != 0x9D || h[24] != 0x01 || h[25] != 0x2A) broken("WebP", "no VP8 start code");
    return info("WebP", le16(h + 26) & 0x3FFF, le16(h + 28) & 0x3FFF);
  }
  if (std::memcmp(h + 12, "VP8L", 4) == 0) {
    if (h[20] != 0x2F) broken("WebP", "no VP8L signature");
    const uint32_t bits = le32(h + 21);
    return info("WebP", (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1);
  }
  if (std::memcmp(h + 12, "VP8X", 4) == 0) {
    const int64_t w = (h[24] | (h[25] << 8) | (h[26] << 16)) + 1;
    return info("WebP", w, (h[27] | (h[28] << 8) | (h[29] << 16)) + 1);
  }
  broken("WebP", "unknown first chunk");
}

bool starts(const uint8_t* h, size_t n, const char* magic, size_t len) {
  return n >= len && std::memcmp(h, magic, len) == 0;
}

}  // namespace

std::optional<ImageFileInfo> parse_image_header(const ByteReader& read) {
  uint8_t h[512];
  const size_t n = read(0, h, sizeof h);
  if (starts(h, n, "\x89PNG\r\n\x1a\n", 8)) {
    if (n < 24 || std::memcmp(h + 12, "IHDR", 4) != 0) broken("PNG", "the first chunk is not IHDR");
    return info("PNG", be32(h + 16), be32(h + 20));
  }
  if (starts(h, n, "\xFF\xD8\xFF", 3)) return jpeg(read);
  if (starts(h, n, "BM", 2)) return bmp(h, n);
  if (n >= 3 && h[0] == 'P' && std::strchr("123456fF7", h[1]) && h[1] != 0 && std::isspace(h[2]))
    return pnm(h, n);
  if (starts(h, n, "II*\0", 4) || starts(h, n, "MM\0*", 4) || starts(h, n, "II+\0", 4) ||
      starts(h, n, "MM\0+", 4)) {
    return tiff(read, h);
  }
  if (starts(h, n, "RIFF", 4) && n >= 12 && std::memcmp(h + 8, "WEBP", 4) == 0) return webp(h, n);
  if (starts(h, n, "\x59\xA6\x6A\x95", 4)) {
    if (n < 12) broken("Sun raster", "the file ends inside the header");
    return info("Sun raster", be32(h + 4), be32(h + 8));
  }
  return std::nullopt;
}

namespace {

struct Fd {
  int fd;
  ~Fd() {
    if (fd >= 0) ::close(fd);
  }
};

const char* file_kind(mode_t mode) {
  if (S_ISDIR(mode)) return "a directory";
  if (S_ISFIFO(mode)) return "a FIFO";
  if (S_ISCHR(mode) || S_ISBLK(mode)) return "a device";
  if (S_ISSOCK(mode)) return "a socket";
  return "not a regular file";
}

std::string megapixels(double pixels) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.1f MP", pixels / 1e6);
  return buf;
}

}  // namespace

ImageFileInfo check_image_file(const std::string& path, int64_t max_pixels) {
  // O_NONBLOCK: opening a FIFO without a writer would otherwise wait for one.
  const Fd f{::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC | O_NOCTTY)};
  if (f.fd < 0) {
    const int err = errno;
    if (err == ENOENT) throw Error(ErrorCode::kNotFound, "no such file");
    throw Error(ErrorCode::kIo, std::string("cannot open: ") + std::strerror(err));
  }
  struct stat st {};
  if (::fstat(f.fd, &st) != 0)
    throw Error(ErrorCode::kIo, std::string("cannot stat: ") + std::strerror(errno));
  if (!S_ISREG(st.st_mode)) {
    throw Error(ErrorCode::kInvalidArgument,
                std::string("not a regular file (") + file_kind(st.st_mode) + ")");
  }
  const ByteReader read = [&f](uint64_t offset, void* buf, size_t n) {
    size_t done = 0;
    while (done < n) {
      const ssize_t r = ::pread(f.fd, static_cast<char*>(buf) + done, n - done,
                                static_cast<off_t>(offset + done));
      if (r < 0 && errno == EINTR) continue;
      if (r < 0) throw Error(ErrorCode::kIo, std::string("cannot read: ") + std::strerror(errno));
      if (r == 0) break;
      done += static_cast<size_t>(r);
    }
    return done;
  };
  const std::optional<ImageFileInfo> info = parse_image_header(read);
  if (!info)
    throw Error(ErrorCode::kUnsupported,
                std::string("not a readable image (not ") + kFormats + ")");
  // Each side is checked alone first: the product of two 32-bit sides can overflow.
  if (info->width > max_pixels || info->height > max_pixels ||
      info->width * info->height > max_pixels) {
    throw Error(
        ErrorCode::kInvalidArgument,
        info->format + " image of " + std::to_string(info->width) + "x" +
            std::to_string(info->height) + " (" +
            megapixels(static_cast<double>(info->width) * static_cast<double>(info->height)) +
            ") is above the limit of " + megapixels(static_cast<double>(max_pixels)) +
            " for image files (kMaxImagePixels); not decoded");
  }
  return *info;
}

cv::Mat read_grey_image(const std::string& path, int64_t max_pixels) {
  check_image_file(path, max_pixels);
  cv::Mat img;
  try {
    img = cv::imread(path, cv::IMREAD_GRAYSCALE);
  } catch (const cv::Exception&) {
    img.release();
  }
  if (img.empty()) throw Error(ErrorCode::kInvalidArgument, "not a readable image");
  return img;
}

}  // namespace posecal
