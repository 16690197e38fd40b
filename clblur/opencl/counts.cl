/* Samples per pixel, shared by the gather (integrate.cl) and the layered compositor
 * (layered.cl): each program's source starts with this file.
 *
 * clblur.motion.sample_counts is the specification: exact ceil(|v|) + 1 from float64 squares
 * of the float32 vector, corrected with exact integer-square comparisons, so that a count
 * never depends on how a platform rounds sqrt.  Only on devices with fp64 (HAVE_FP64, a
 * build option set from the device's capabilities); elsewhere the host counts.
 */
#pragma OPENCL FP_CONTRACT OFF

#ifdef HAVE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

static int sample_count(float vx, float vy)
{
    double x = vx, y = vy;
    double l2 = x * x + y * y;
    double m = ceil(sqrt(l2));
    m = m * m < l2 ? m + 1.0 : m;
    m = m > 0.0 && (m - 1.0) * (m - 1.0) >= l2 ? m - 1.0 : m;
    return (int)m + 1;
}
#endif
